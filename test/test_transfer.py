"""Device-to-host reads of several arrays with one wait, and host-to-device uploads without one
(soft_tissue_sim.transfer).

Warp's CPU backend by default; ``STS_TEST_DEVICE=cuda:0`` goes through pinned mirrors."""

import os

import numpy as np
import warp as wp

from soft_tissue_sim.transfer import Staged, to_host

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")


def test_to_host_reads_every_array_and_follows_later_writes():
    rng = np.random.default_rng(0)
    a_np, b_np = rng.standard_normal((7, 3)), rng.integers(0, 9, 11).astype(np.int32)
    a = wp.array(a_np, dtype=wp.vec3d, device=DEVICE)
    b = wp.array(b_np, dtype=wp.int32, device=DEVICE)
    ha, hb = to_host(a, b)
    np.testing.assert_array_equal(ha, a_np)
    np.testing.assert_array_equal(hb, b_np)
    a.assign(2.0 * a_np)  # a later read sees the new values (the mirror is refilled)
    (ha2,) = to_host(a)
    np.testing.assert_array_equal(ha2, 2.0 * a_np)
    assert ha2.shape == (7, 3) and hb.dtype == np.int32


def test_staged_uploads_what_the_host_wrote_and_a_refill_never_changes_a_sent_copy():
    s = Staged((5, 4), wp.int32, DEVICE)
    first = np.arange(20, dtype=np.int32).reshape(5, 4)
    s.view()[:] = first
    sent = s.send()
    assert sent is s.array
    copy1 = wp.clone(sent)  # ordered after the upload on the stream
    s.view()[:2] = -1  # refilled after the send: waits for the copy to have left
    s.send(count=8)  # the first two rows only
    np.testing.assert_array_equal(copy1.numpy(), first)
    expect = first.copy()
    expect[:2] = -1
    np.testing.assert_array_equal(s.array.numpy(), expect)


def test_pinned_pool_recycles_blocks_by_size_and_keeps_a_lent_one_apart():
    from soft_tissue_sim.transfer import PinnedPool

    pool = PinnedPool(pinned=DEVICE != "cpu")
    a = pool.zeros(7, wp.vec3d)  # 168 bytes: a 256-byte block
    assert a.shape == (7,) and a.device.is_cpu and a.pinned == pool.pinned
    np.testing.assert_array_equal(a.numpy(), 0.0)
    a.numpy()[:] = 5.0
    b = pool.empty(30, wp.float64)  # 240 bytes: another 256-byte block, a is still lent
    assert b.ptr != a.ptr and pool.allocated == 2
    ptr = a.ptr
    del a  # its block goes back to the pool ...
    c = pool.zeros((5, 4), wp.int32)  # ... and is the one handed out next, zeroed
    assert c.ptr == ptr and pool.allocated == 2
    np.testing.assert_array_equal(c.numpy(), 0)
    d = pool.empty(1000, wp.float64)  # 8000 bytes: a new 8 KiB block
    assert d.ptr not in (ptr, b.ptr) and pool.allocated == 3
    if DEVICE != "cpu":  # a device read through a pooled mirror
        src = wp.array(np.arange(30.0), dtype=wp.float64, device=DEVICE)
        wp.copy(b, src)
        wp.synchronize_device(DEVICE)
        np.testing.assert_array_equal(b.numpy(), np.arange(30.0))



def test_a_mirror_follows_its_source_through_shape_changes_on_one_block():
    """The views of one allocation at several lengths (the state after mesh changes) are read
    through one mirror per address: a new length gives the old mirror's block back to the pool,
    which hands it out again, instead of a new page-locked block per length."""
    from soft_tissue_sim import transfer as T

    pool = T.PinnedPool(pinned=DEVICE != "cpu")
    rng = np.random.default_rng(2)
    full = rng.standard_normal((90, 3))
    buf = wp.array(full, dtype=wp.vec3d, device=DEVICE)
    for n in (60, 70, 55, 64):  # 1,320-1,680 bytes: one 2 KiB size class
        view = buf[:n]
        m = T._mirror(view, pool)
        assert m.shape == (n,) and m.dtype == wp.vec3d
        wp.copy(m, view)
        wp.synchronize_device(DEVICE)
        np.testing.assert_array_equal(m.numpy(), full[:n])
        del m
        if DEVICE != "cpu":
            (h,) = to_host(view)
            np.testing.assert_array_equal(h, full[:n])
            del h
    assert pool.allocated == 1
