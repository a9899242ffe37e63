"""The contact LCP by projected Gauss-Seidel (soft_tissue_sim.contact.pgs) against an exact
solution by enumeration of the active sets, and the friction cone."""

import itertools

import numpy as np
import pytest

from soft_tissue_sim.contact.pgs import PGS


def _spd(rng, m):
    A = rng.standard_normal((m, m))
    W = A @ A.T + 0.5 * m * np.eye(m)
    return 0.5 * (W + W.T)


def _lcp_by_enumeration(W, d0):
    """The solution of 0 <= W lam + d0 _|_ lam >= 0 (W positive definite: unique)."""
    m = len(d0)
    for k in range(m + 1):
        for act in itertools.combinations(range(m), k):
            act = list(act)
            lam = np.zeros(m)
            if act:
                lam[act] = np.linalg.solve(W[np.ix_(act, act)], -d0[act])
            d = W @ lam + d0
            if (lam >= -1e-12).all() and (d >= -1e-12).all():
                return lam
    raise AssertionError("no solution")


@pytest.mark.parametrize("seed", range(6))
def test_frictionless_pgs_equals_the_exact_lcp_solution(seed):
    rng = np.random.default_rng(seed)
    m = 7
    W = _spd(rng, m)
    d0 = rng.standard_normal(m)  # some rows pressed (d0 < 0), some apart
    ref = _lcp_by_enumeration(W, d0)
    rows = np.ones(m, np.int32)
    lam0 = np.abs(rng.standard_normal(m)) * (seed % 2)  # cold and warm starts
    lam, its, res = PGS().solve(W, d0, np.arange(m, dtype=np.int32), rows, np.zeros(m), 5000, 1e-13, False, lam0)
    assert res <= 1e-13 and its < 5000
    np.testing.assert_allclose(lam, ref, atol=1e-10 * np.abs(ref).max())
    assert 0 < (ref > 0).sum() < m  # both kinds of rows present


@pytest.mark.parametrize("pyramid", [False, True])
def test_friction_stays_in_its_cone_and_the_normal_rows_are_complementary(pyramid):
    rng = np.random.default_rng(7)
    k = 5
    m = 3 * k
    W = _spd(rng, m)
    d0 = rng.standard_normal(m)
    d0[::3] = -np.abs(d0[::3])  # every contact pressed
    mu = np.full(k, 0.4)
    lam, its, res = PGS().solve(W, d0, np.arange(0, m, 3, dtype=np.int32), np.full(k, 3, np.int32), mu, 20000,
                                1e-12, pyramid, np.zeros(m))
    assert res <= 1e-12
    ln, t = lam[::3], np.stack([lam[1::3], lam[2::3]], axis=1)
    d = W @ lam + d0
    assert (ln >= 0).all() and np.all(np.abs(ln * d[::3]) <= 1e-10) and (d[::3] >= -1e-10).all()
    lim = mu * ln
    if pyramid:
        assert (np.abs(t) <= lim[:, None] + 1e-12).all()
    else:
        assert (np.linalg.norm(t, axis=1) <= lim + 1e-12).all()
    # a sticking contact (strictly inside its cone) has no tangential motion
    inside = np.linalg.norm(t, axis=1) < lim - 1e-9 if not pyramid else (np.abs(t) < lim[:, None] - 1e-9).all(axis=1)
    for c in np.flatnonzero(inside):
        assert np.abs(d[3 * c + 1: 3 * c + 3]).max() <= 1e-8


def test_a_reused_solver_solves_each_problem_as_a_fresh_one():
    """PGS keeps its buffers between solves (sized to the largest problem seen): a larger
    problem, then smaller ones (stale rows beyond them in the buffers), then a larger one again,
    each equal to the exact LCP solution and to a fresh solver's answer."""
    rng = np.random.default_rng(3)
    pgs = PGS()
    for m in (20, 7, 3, 7, 40):
        W = _spd(rng, m)
        d0 = rng.standard_normal(m)
        args = (W, d0, np.arange(m, dtype=np.int32), np.ones(m, np.int32), np.zeros(m), 5000, 1e-13, False,
                np.zeros(m))
        lam, its, res = pgs.solve(*args)
        fresh = PGS().solve(*args)
        assert res <= 1e-13 and its < 5000
        np.testing.assert_array_equal(lam, fresh[0])
        assert (its, res) == fresh[1:]
        if m <= 7:
            ref = _lcp_by_enumeration(W, d0)
            np.testing.assert_allclose(lam, ref, atol=1e-10 * np.abs(ref).max())
    assert pgs.rows_cap == 40
