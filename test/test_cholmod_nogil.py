"""CHOLMOD through ctypes (cholmod_nogil): the same factor as scikit-sparse, and the GIL free
while it factorizes, so that the asynchronous preconditioner's thread runs beside the step."""

import threading
import time

import numpy as np
import pytest
import scipy.sparse as sps
from sksparse.cholmod import analyze as sk_analyze

from soft_tissue_sim import cholmod_nogil as cn
from soft_tissue_sim import load_scene



def test_the_pinned_cholmod_is_bound():
    """The install pins SuiteSparse 5 (CHOLMOD 3), whose layouts the module binds."""
    assert cn.available(), cn.unavailable_reason()


def laplacian(m, shift=0.5):
    """SPD 3D grid operator (m^3 unknowns): a factorization with real fill."""
    I = sps.identity(m)
    T = sps.diags([-1.0, 2.0 + shift, -1.0], [-1, 0, 1], shape=(m, m))
    return (sps.kron(sps.kron(T, I), I) + sps.kron(sps.kron(I, T), I) + sps.kron(sps.kron(I, I), T)).tocsc()


def sk_factor(A, ordering):
    f = sk_analyze(A, mode="simplicial", ordering_method=ordering).copy()
    f.cholesky_inplace(A)
    return f


@pytest.mark.parametrize("ordering", ["default", "amd", "metis", "nesdis", "natural"])
def test_factor_solve_permutation_and_LD_are_scikit_sparses(ordering):
    rng = np.random.default_rng(0)
    A = laplacian(7)
    A = (A + sps.diags(rng.uniform(0.0, 1.0, A.shape[0]))).tocsc()  # not a multiple of a stencil
    f = cn.analyze(A, ordering).factorized(A)
    g = sk_factor(A, ordering)
    np.testing.assert_array_equal(f.P(), g.P())
    LD, LDg = f.LD(), g.LD()
    assert LD.nnz == LDg.nnz and abs(LD - LDg).max() == 0.0  # the same numbers: one library
    # column j of LD starts with D_jj (what delassus.LowerFactor reads)
    assert np.array_equal(LD.indices[LD.indptr[:-1]], np.arange(A.shape[0]))
    B = rng.standard_normal((A.shape[0], 3))
    X = f(B)
    np.testing.assert_allclose(A @ X, B, atol=1e-12)
    np.testing.assert_allclose(f(B[:, 1]), X[:, 1], rtol=0, atol=1e-14)  # a vector gives a vector
    # and L D L^T reproduces the permuted matrix
    n = A.shape[0]
    d = LD.diagonal()
    L = sps.tril(LD, -1) + sps.identity(n)
    p = f.P()
    assert abs(L @ sps.diags(d) @ L.T - A[p][:, p]).max() < 1e-12


def test_one_symbolic_analysis_serves_several_numeric_factors():
    A = laplacian(6)
    sym = cn.analyze(A)
    f1 = sym.factorized(A)
    A2 = (A * 3.0).tocsc()
    f2 = sym.factorized(A2)  # same pattern, other numbers; f1 untouched
    b = np.ones(A.shape[0])
    np.testing.assert_allclose(A @ f1(b), b, atol=1e-12)
    np.testing.assert_allclose(A2 @ f2(b), b, atol=1e-12)
    with pytest.raises(cn.CholmodError, match="symbolic"):
        sym(b)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="square"):
        cn.analyze(sps.csc_matrix(np.ones((3, 4))))
    with pytest.raises(ValueError, match="ordering"):
        cn.analyze(laplacian(3), "best")


def _longest_stall(factorize):
    """Run ``factorize`` in a thread; the main thread meanwhile ticks in pure Python. Returns the
    longest gap between ticks inside the window [call start, call end], and the window."""
    ticks, window = [], {}
    started, finished = threading.Event(), threading.Event()

    def work():
        started.set()
        window["t0"] = time.perf_counter()
        factorize()
        window["t1"] = time.perf_counter()
        finished.set()

    th = threading.Thread(target=work)
    th.start()
    started.wait()
    while not finished.is_set():
        ticks.append(time.perf_counter())
    th.join()
    t = np.array([window["t0"]] + [x for x in ticks if window["t0"] < x < window["t1"]] + [window["t1"]])
    return float(np.diff(t).max()), window["t1"] - window["t0"]


def test_the_gil_is_free_while_cholmod_factorizes_and_held_by_scikit_sparse():
    """The point of the module: with scikit-sparse the main thread stands still for the whole
    numeric factorization (the control); through ctypes it keeps running."""
    A = laplacian(20)  # 8,000 unknowns: about 0.1 s of factorization
    sym, sk_sym = cn.analyze(A), sk_analyze(A, mode="simplicial")
    stall, window = _longest_stall(lambda: sym.factorized(A))
    sk_stall, sk_window = _longest_stall(lambda: sk_sym.copy().cholesky_inplace(A))
    assert sk_window > 0.03 and sk_stall > 0.5 * sk_window, (sk_stall, sk_window)  # the GIL held
    assert stall < 0.25 * window, (stall, window)  # the main thread ran throughout


def test_the_preconditioner_factorizes_without_the_gil_unless_told_not_to():
    def beam(**ldlt):
        return {"device": "cpu", "mesh": {"generator": "beam", "n_long": 8, "n_cross": 3, "spacing": 0.01},
                "materials": [{"id": 0, "young": 5e4, "poisson": 0.3, "density": 1000.0}],
                "fixed": {"axis": "x", "below": 0.0}, "time": {"dt": 0.01},
                "solver": {"preconditioner": "async_ldlt", "tolerance": 1e-8,
                           "ldlt": {"deterministic": True, "refresh_every": 1, **ldlt}}}

    runs = {}
    for release in (True, False):
        with load_scene(beam(release_gil=release)) as sim:
            its = [sim.step().iterations for _ in range(4)]
            runs[release] = (sim.positions(), its, sim.preconditioner.stats())
    assert runs[True][2]["factorization_gil_free"] is True
    assert runs[False][2]["factorization_gil_free"] is False
    assert runs[True][1] == runs[False][1] and max(runs[True][1]) <= 2  # a fresh exact factor each step
    np.testing.assert_allclose(runs[True][0], runs[False][0], rtol=0, atol=1e-13)
    with load_scene(beam(mode="supernodal")) as sim:  # supernodal: scikit-sparse (not bound here)
        sim.step()
        assert sim.preconditioner.stats()["factorization_gil_free"] is False


def test_a_layout_that_does_not_match_is_refused(monkeypatch):
    """The offsets are checked against CHOLMOD itself when the library is loaded; a wrong one
    (here the status field moved by 8 bytes) makes the module refuse, and the preconditioner
    then uses scikit-sparse."""
    assert cn.available()
    monkeypatch.setattr(cn, "_lib", None)
    monkeypatch.setattr(cn, "_why", None)
    monkeypatch.setattr(cn, "_C_STATUS", cn._C_STATUS + 8)
    assert not cn.available()
    assert "layout" in cn.unavailable_reason()
    with pytest.raises(cn.CholmodError, match="not available"):
        cn.analyze(laplacian(3))
