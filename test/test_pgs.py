"""The contact LCP (soft_tissue_sim.contact.pgs): projected Gauss-Seidel and the active-set
finish of a frictionless LCP against an exact solution by enumeration of the active sets, on
near-singular W like the resection's (where the sweeps alone stall), against the sweeps alone
on well-conditioned problems, and the friction cone; the active-set finish with friction on the
default scene's own LCPs."""

import itertools

import numpy as np
import pytest

from lcp_reference import pgs_residual_host, solve_reference
from soft_tissue_sim.contact.pgs import FIRST_SWEEPS, PGS, active_set, face_solve, frictionless_residual


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


# ------------------------------------------------ the active-set finish of a frictionless LCP
def _frictionless(W, d0, max_iterations=200, tolerance=1e-8, lam0=None):
    m = len(d0)
    return (W, d0, np.arange(m, dtype=np.int32), np.ones(m, np.int32), np.zeros(m), max_iterations, tolerance,
            False, np.zeros(m) if lam0 is None else lam0)


def _clustered(seed, k=30, r=8, n=90, pressed=20):
    """A near-singular W like the resection's: k contacts on nearly r points (each row a
    barycentric-like mix of r base rows, plus a perturbation of 1e-4 to 1e-1 of its own), so
    that W = H A^-1 H^T has eigenvalues down to about 1e-8 of the largest; scaled to the
    resection's diagonal (4e-3 m/N) and gaps (about -1 mm). delta^0 is made from a known
    solution lambda* with ``pressed`` rows pressed and the others apart by up to 0.1 mm."""
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((n, n))
    A = B @ B.T + n * np.eye(n)
    mix = rng.random((k, r)) ** 4
    H = (mix / mix.sum(axis=1, keepdims=True)) @ rng.standard_normal((r, n))
    H += 10.0 ** rng.uniform(-4, -1, (k, 1)) * rng.standard_normal((k, n))
    W = H @ np.linalg.solve(A, H.T)
    W = 0.5 * (W + W.T) * (4e-3 / np.mean(np.diag(H @ np.linalg.solve(A, H.T))))
    lam = np.zeros(k)
    on = rng.choice(k, pressed, replace=False)
    lam[on] = 0.05 * rng.random(pressed)
    delta = 1e-4 * rng.random(k)
    delta[on] = 0.0
    return W, delta - W @ lam, lam


def _assert_complementary(W, d0, lam, tol):
    d = W @ lam + d0
    assert (lam >= 0).all()
    assert (d >= -tol).all()
    assert np.abs(d[lam > 0]).max(initial=0.0) <= tol


@pytest.mark.parametrize("seed", range(6))
def test_the_active_set_finish_reaches_the_tolerance_where_the_sweeps_alone_stall(seed):
    W, d0, ref = _clustered(seed)
    e = np.linalg.eigvalsh(W)
    assert e[0] < 1e-7 * e[-1]  # near singular
    tol = 1e-8
    lam_gs, its_gs, res_gs = PGS(active_set=False).solve(*_frictionless(W, d0))
    assert its_gs == 200 and res_gs > 10 * tol  # the sweeps alone stop at the cap, far from the tolerance
    lam, its, res = PGS().solve(*_frictionless(W, d0))
    assert res <= tol and its <= 40
    assert res == pytest.approx(frictionless_residual(W, d0, lam), rel=1e-6, abs=1e-18)
    _assert_complementary(W, d0, lam, tol)
    # lambda is not unique where W is singular; delta = W lambda + d0 is (up to the tolerance)
    assert np.abs(W @ (lam - ref)).max() <= 3 * tol
    assert np.abs(W @ (lam_gs - ref)).max() > 3 * tol


@pytest.mark.parametrize("seed", range(6))
def test_the_active_set_method_alone_equals_the_exact_lcp_solution(seed):
    """From a cold start (every row leaves the passive set's empty start by joining it) and from
    a wrong warm start (rows passive that are apart at the solution, rows apart that are
    pressed), on positive definite problems with a unique solution."""
    rng = np.random.default_rng(seed)
    m = 7
    W = _spd(rng, m)
    d0 = rng.standard_normal(m)
    ref = _lcp_by_enumeration(W, d0)
    for start in (np.zeros(m), np.where(ref > 0, 0.0, 1.0 + rng.random(m))):
        lam, steps = active_set(W, d0, start, 1e-13, 100)
        assert steps < 100
        np.testing.assert_allclose(lam, ref, atol=1e-12 * np.abs(ref).max())
        assert frictionless_residual(W, d0, lam) <= 1e-13


def test_repeated_rows_make_w_singular_and_share_their_force():
    """Rows repeated exactly (a node contact and a face contact at the node): W singular, the
    face solve's shifted factor still defined; the result complementary, its normal force
    sum per repeated pair fixed by W lambda."""
    rng = np.random.default_rng(4)
    W, d0, _ = _clustered(1)
    rep = np.concatenate([np.arange(len(d0)), rng.choice(len(d0), 8, replace=False)])
    Wr, dr = W[np.ix_(rep, rep)], d0[rep]
    assert np.linalg.eigvalsh(Wr)[0] < 1e-17 * np.linalg.eigvalsh(Wr)[-1]
    lam, its, res = PGS().solve(*_frictionless(Wr, dr))
    assert res <= 1e-8 and its < 200
    _assert_complementary(Wr, dr, lam, 1e-8)
    single, _, _ = PGS().solve(*_frictionless(W, d0))
    np.testing.assert_allclose(Wr @ lam + dr, (W @ single + d0)[rep], atol=2e-8)


def test_the_face_solve_refuses_an_indefinite_face_and_refines_a_shifted_one():
    W = np.array([[1.0, 2.0], [2.0, 1.0]])
    assert face_solve(W, np.array([1.0, 1.0]), np.arange(2), 1e-12) is None
    rng = np.random.default_rng(0)
    W = _spd(rng, 6)
    d0 = rng.standard_normal(6)
    rows = np.array([0, 2, 3, 5])
    shift = 1e-2  # large: the refinement takes out all but a fraction shift / lambda_min of its error
    Wpp = W[np.ix_(rows, rows)]
    exact = np.linalg.solve(Wpp, -d0[rows])
    unrefined = np.linalg.solve(Wpp + shift * np.eye(4), -d0[rows])
    error = np.linalg.norm(face_solve(W, d0, rows, shift) - exact)
    assert error <= shift / np.linalg.eigvalsh(Wpp)[0] * np.linalg.norm(unrefined - exact)
    assert np.linalg.norm(unrefined - exact) > 1e-4  # the shift's error is there to take out


def test_where_a_face_is_indefinite_the_sweeps_go_on_and_report_their_residual():
    """ContactSolver never passes an indefinite W (it falls back to the diagonal compliance);
    if one comes, the active-set method stops at the first face that is not positive definite
    (one face solve) and the sweeps take the rest of the budget from the better lambda, the
    residual reported being that of the lambda returned. An empty problem is its own
    solution."""
    W = np.array([[1.0, 2.0], [2.0, 1.0]])
    d0 = np.array([-1.0, -1.0])
    lam0 = np.array([1.0, 1.0])  # both passive: the face W itself, indefinite
    lam, steps = active_set(W, d0, lam0, 1e-8, 50)
    assert steps == 1
    np.testing.assert_array_equal(lam, lam0)
    lam, its, res = PGS(first_sweeps=0).solve(*_frictionless(W, d0, 30, 1e-8, lam0))
    swept, sweeps, _ = PGS(active_set=False).solve(*_frictionless(W, d0, 30, 1e-8, lam0))
    assert its == 1 + sweeps and res <= 1e-8  # the face solve, then the sweeps from lam0 (the better)
    np.testing.assert_array_equal(lam, swept)
    assert res == pytest.approx(frictionless_residual(W, d0, lam), abs=1e-15)
    _assert_complementary(W, d0, lam, 1e-8)
    lam, steps = active_set(np.zeros((0, 0)), np.zeros(0), np.zeros(0), 1e-8, 10)
    assert lam.shape == (0,) and steps == 0


@pytest.mark.parametrize("max_iterations", [5, 12, 20])
def test_sweeps_and_active_set_steps_share_the_iteration_budget(max_iterations):
    """sweeps = Gauss-Seidel sweeps + face solves <= max_iterations, and the residual reported
    is the returned lambda's."""
    W, d0, _ = _clustered(0)
    lam, its, res = PGS().solve(*_frictionless(W, d0, max_iterations))
    assert its <= max_iterations
    assert res == pytest.approx(frictionless_residual(W, d0, lam), rel=1e-6, abs=1e-18)
    assert (lam >= 0).all()


@pytest.mark.parametrize("seed", range(4))
def test_on_well_conditioned_problems_the_finish_agrees_with_the_sweeps_alone(seed):
    """Frictionless, warm and cold, m = 40 (many sweeps to converge at a tight tolerance): the
    same solution as the sweeps alone within the tolerance, in fewer sweeps."""
    rng = np.random.default_rng(seed)
    m = 40
    A = rng.standard_normal((m, m))
    W = A @ A.T / m + 0.05 * np.eye(m)  # condition number about 100: the sweeps need many
    W = 0.5 * (W + W.T)
    d0 = rng.standard_normal(m)
    lam0 = np.abs(rng.standard_normal(m)) * (seed % 2)
    tol = 1e-11
    lam_gs, its_gs, res_gs = PGS(active_set=False).solve(*_frictionless(W, d0, 5000, tol, lam0))
    lam, its, res = PGS().solve(*_frictionless(W, d0, 5000, tol, lam0))
    assert res_gs <= tol and res <= tol and its < its_gs
    smallest = np.linalg.eigvalsh(W)[0]
    np.testing.assert_allclose(lam, lam_gs, atol=4 * tol / smallest)
    np.testing.assert_array_equal(lam > 1e-9, lam_gs > 1e-9)


@pytest.mark.parametrize("pyramid", [False, True])
def test_with_friction_rows_the_solver_sweeps_as_without_the_finish(pyramid):
    """Friction (every contact, or some of them) keeps the sweeps alone: the same lambda,
    sweeps and residual as PGS(active_set=False)."""
    rng = np.random.default_rng(11)
    k = 6
    rows = np.array([3, 1, 3, 3, 1, 3], np.int32)
    for rows_ in (np.full(k, 3, np.int32), rows):
        m = int(rows_.sum())
        W = _spd(rng, m)
        d0 = rng.standard_normal(m)
        row_start = (np.cumsum(rows_) - rows_).astype(np.int32)
        d0[row_start] = -np.abs(d0[row_start])
        mu = np.where(rows_ == 3, 0.4, 0.0)
        args = (W, d0, row_start, rows_, mu, 300, 1e-10, pyramid, np.zeros(m))
        new, old = PGS().solve(*args), PGS(active_set=False).solve(*args)
        np.testing.assert_array_equal(new[0], old[0])
        assert new[1:] == old[1:]


# --------------------------------------------------- the active-set finish of an LCP with friction
def _friction_problem(rng, rows_):
    m = int(rows_.sum())
    W = _spd(rng, m)
    d0 = rng.standard_normal(m)
    row_start = (np.cumsum(rows_) - rows_).astype(np.int32)
    d0[row_start] = -np.abs(d0[row_start])
    return W, d0, row_start, np.asarray(rows_, np.int32), np.where(rows_ == 3, 0.4, 0.0)


@pytest.mark.parametrize("pyramid", [False, True])
def test_the_hosts_residual_is_the_kernels(pyramid):
    """pgs_residual_host (what the friction finish scores its iterates by) equals the kernel's
    residual of the same lambda (a solve of 0 sweeps), up to the order of delta's sums: at cold
    and warm starts, inside and outside the cones, with one-row contacts among the others."""
    rng = np.random.default_rng(5)
    for rows_ in (np.full(5, 3), np.array([3, 1, 3, 1, 1, 3])):
        W, d0, row_start, rows_, mu = _friction_problem(rng, rows_)
        m, nc = len(d0), len(row_start)
        pgs = PGS(active_set=False)
        pgs.solve(W, d0, row_start, rows_, mu, 1, 1e-9, pyramid, np.zeros(m))  # fills the kernel's buffers
        for lam in (np.zeros(m), np.abs(rng.standard_normal(m)), 0.1 * rng.standard_normal(m)):
            kernel = pgs._sweeps(lam, m, nc, 0, 1e-9, pyramid)[2]
            assert kernel > 0.0
            assert pgs_residual_host(W, d0, lam, row_start, rows_, mu, pyramid) == pytest.approx(kernel, rel=1e-12)


@pytest.fixture(scope="module")
def default_scene_lcps():
    """The LCPs the host solves along the first 400 steps of the node benchmark's trajectory in
    the default scene (the scalpel lowered onto the tissue and pressed; friction 0.2)."""
    from soft_tissue_sim.bench.lcp import default_sets

    return default_sets(400, 1)


def test_the_friction_finish_converges_where_the_sweeps_stop_at_their_cap(default_scene_lcps):
    """The scalpel's tip presses a node and the faces around it: nearly one constraint several
    times, where the sweeps alone end at max_iterations above the tolerance in about a tenth of
    the steps. With the finish most of those converge, the iterations (sweeps and steps) fall by
    more than half, and every answer keeps lambda_n >= 0 and the forces in their cones."""
    plain, finish = PGS(), PGS(friction_active_set=True)
    hard = converged = 0
    its_plain = its_finish = 0
    for W, d0, row_start, rows_, mu, lam0, tol, pyramid, max_iterations in default_scene_lcps:
        assert (rows_ == 3).all() and not pyramid
        a = plain.solve(W, d0, row_start, rows_, mu, max_iterations, tol, pyramid, lam0)
        lam, its, res = finish.solve(W, d0, row_start, rows_, mu, max_iterations, tol, pyramid, lam0)
        assert its == solve_reference(W, d0, row_start, rows_, mu, max_iterations, tol, pyramid, lam0)[1]
        assert its <= max_iterations
        assert res == pytest.approx(pgs_residual_host(W, d0, lam, row_start, rows_, mu, pyramid), rel=1e-9, abs=1e-18)
        ln = lam[row_start]
        assert (ln >= 0.0).all()
        assert (np.hypot(lam[row_start + 1], lam[row_start + 2]) <= mu * ln * (1 + 1e-12) + 1e-300).all()
        its_plain, its_finish = its_plain + a[1], its_finish + its
        if a[2] > tol:
            hard += 1
            converged += res <= tol
    assert len(default_scene_lcps) > 200 and hard >= 10
    assert converged >= hard / 2
    assert its_finish < 0.5 * its_plain


@pytest.mark.parametrize("pyramid", [False, True])
def test_the_kernels_friction_finish_is_the_references(pyramid):
    """PGS with friction_active_set (the finish inside the host's kernel) against the same solve
    written in NumPy and LAPACK (test/lcp_reference.py): the same iterations and verdicts, and
    where converged the same contact displacement to rounding, on problems the first sweeps do
    not solve (W of nearly repeated rows, 1e-12 m) and others, with one-row contacts among
    the others."""
    rng = np.random.default_rng(9)
    stalled = converged = 0  # trials beyond the first sweeps, and converged
    for trial in range(12):
        rows_ = np.array([3, 3, 1, 3, 3]) if trial % 3 == 2 else np.full(5, 3)
        m = int(rows_.sum())
        base = rng.standard_normal((m, 4 if trial % 2 else m))  # rank 4: nearly repeated rows
        W = base @ base.T + (1e-6 if trial % 2 else 0.5) * np.eye(m)
        row_start = (np.cumsum(rows_) - rows_).astype(np.int32)
        d0 = 0.1 * rng.standard_normal(m)
        d0[row_start] = -np.abs(d0[row_start])
        mu = np.where(rows_ == 3, 0.3, 0.0)
        args = (W, d0, row_start, rows_.astype(np.int32), mu, 200, 1e-12, pyramid, np.zeros(m))
        lam, its, res = PGS(friction_active_set=True).solve(*args)
        ref, its_ref, res_ref = solve_reference(*args)
        assert its == its_ref and (res <= 1e-12) == (res_ref <= 1e-12)
        assert res == pytest.approx(res_ref, rel=1e-6, abs=1e-15)  # below that, rounding
        if res <= 1e-12:  # a solution: the contact displacement W lambda the reference's (the split
            # between nearly repeated rows may differ by rounding where the sweeps stopped early)
            np.testing.assert_allclose(W @ lam, W @ ref, rtol=0, atol=1e-9 * np.abs(W @ ref).max())
            converged += 1
        stalled += its > FIRST_SWEEPS
    assert stalled >= 3 and converged >= 6  # the finish ran in some (beyond the first sweeps)


def test_without_friction_the_friction_finish_changes_nothing():
    """A frictionless LCP goes to the frictionless active-set method either way."""
    W, d0, lam_star = _clustered(1)
    args = _frictionless(W, d0, tolerance=1e-10)
    a, b = PGS().solve(*args), PGS(friction_active_set=True).solve(*args)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1:] == b[1:]


def test_beyond_its_row_limit_the_friction_finish_leaves_the_sweeps_alone():
    """A set with friction of more than FRICTION_FINISH_ROWS rows (one thread's normal
    equations grow as the cube of the rows): the sweeps alone, as without the option; within the
    limit the same problem's first rows are finished."""
    from soft_tissue_sim.contact.pgs import FRICTION_FINISH_ROWS

    rng = np.random.default_rng(12)
    k = FRICTION_FINISH_ROWS // 3 + 1
    m = 3 * k
    base = rng.standard_normal((m, 30))
    W = base @ base.T + 1e-6 * np.eye(m)  # of rank 30 and 66 rows: the sweeps take tens
    d0 = 0.1 * rng.standard_normal(m)
    d0[::3] = -np.abs(d0[::3])
    row_start, rows_, mu = np.arange(0, m, 3, dtype=np.int32), np.full(k, 3, np.int32), np.full(k, 0.3)
    args = (W, d0, row_start, rows_, mu, 200, 1e-9, False, np.zeros(m))
    on, off = PGS(friction_active_set=True).solve(*args), PGS().solve(*args)
    np.testing.assert_array_equal(on[0], off[0])
    assert on[1:] == off[1:] and on[1] > FIRST_SWEEPS
    j = 3 * (FRICTION_FINISH_ROWS // 3)  # the first contacts, within the limit: finished
    small = (W[:j, :j], d0[:j], row_start[:j // 3], rows_[:j // 3], mu[:j // 3], 200, 1e-9, False, np.zeros(j))
    fin, plain = PGS(friction_active_set=True).solve(*small), PGS().solve(*small)
    assert plain[1] > FIRST_SWEEPS and fin[1] != plain[1]
