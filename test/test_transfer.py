"""Device-to-host reads of several arrays with one wait (soft_tissue_sim.transfer).

Warp's CPU backend by default; ``STS_TEST_DEVICE=cuda:0`` reads through pinned mirrors."""

import os

import numpy as np
import warp as wp

from soft_tissue_sim.transfer import to_host

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
