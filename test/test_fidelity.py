"""Fidelity on stiff and extreme cases (issue 23): symmetric meshes bend in their symmetry
plane, an optional re-linearised (Newton) step that creates no energy, convergence judged on
the true residual, the state round trip, clear errors for empty or unreadable mesh files, and
a rigid sphere indenting a block against Hertz, frictionless and fully stuck."""

import meshio
import numpy as np
import pytest

from soft_tissue_sim import ParameterError, load_scene
from soft_tissue_sim.bench.stability import beam as stability_beam
from soft_tissue_sim.cg import DevicePCG
from soft_tissue_sim.mesh import MeshError, beam_mesh, brain_mesh, load_mesh, save_mesh, validate_mesh
from test_contact import inside_any_tet, scene

G = 9.81


# ------------------------------------------------------------------ symmetric meshes
def _mirror_map(points, axis):
    """Node permutation of the mirror x_axis -> -x_axis (about the mesh's mid-plane)."""
    c = 0.5 * (points[:, axis].min() + points[:, axis].max())
    q = points.copy()
    q[:, axis] = 2.0 * c - q[:, axis]
    key = {tuple(np.round(p, 9)): i for i, p in enumerate(points)}
    return np.array([key[tuple(np.round(p, 9))] for p in q])


def _is_symmetric(mesh, axis):
    perm = _mirror_map(mesh.points, axis)
    tets = {tuple(t) for t in np.sort(mesh.tets, axis=1)}
    return tets == {tuple(t) for t in np.sort(perm[mesh.tets], axis=1)}


@pytest.mark.parametrize("make,axes", [(lambda s: beam_mesh(12, 5, split=s), (1, 2)),
                                       (lambda s: brain_mesh(split=s), (0, 1))])
def test_mirrored_split_is_symmetric_under_the_shape_mirrors(make, axes):
    m, u = make("mirrored"), make("uniform")
    for axis in axes:
        assert _is_symmetric(m, axis)
        assert not _is_symmetric(u, axis)  # the old split is not: the check can fail
    assert m.n_tets == u.n_tets and m.signed_volumes().min() > 0
    # the same cells (a mapped cell's volume depends a little on its split)
    assert m.signed_volumes().sum() == pytest.approx(u.signed_volumes().sum(), rel=1e-4)
    # conforming: the only faces used once are the 2 triangles of each boundary quad
    assert len(m.boundary_faces()) == len(u.boundary_faces())


def _tip_ratio(split, poisson):
    """Static sag of a 5 x 5 x 40 node cantilever under gravity: tip (u_y / u_z, u_z)."""
    cfg = {"device": "cpu", "mesh": {"generator": "beam", "n_long": 40, "n_cross": 5, "spacing": 0.01, "split": split},
           "materials": [{"id": 0, "young": 1e7, "poisson": poisson, "density": 1000.0}],
           "damping": {"mass": 0.0, "stiffness": 0.0}, "gravity": [0.0, 0.0, -G],
           "fixed": {"axis": "x", "below": 0.0}, "time": {"dt": 100.0},
           "solver": {"preconditioner": "direct", "tolerance": 1e-10, "max_iterations": 100}}
    with load_scene(cfg) as sim:
        for _ in range(3):
            sim.step()
        u = sim.positions() - sim.mesh.points
        tip = sim.mesh.points[:, 0] > sim.mesh.points[:, 0].max() - 1e-9
        return u[tip, 1].mean() / u[tip, 2].mean(), u[tip, 2].mean()


@pytest.mark.parametrize("poisson", [0.3, 0.499])
def test_a_beam_loaded_in_its_symmetry_plane_bends_in_it(poisson):
    ratio, sag = _tip_ratio("mirrored", poisson)
    assert sag < 0.0 and abs(ratio) <= 1e-3, ratio
    old, _ = _tip_ratio("uniform", poisson)  # the single-diagonal split leans sideways
    assert abs(old) > 0.05, old


# ------------------------------------------------------------------ energy-safe step
def _soft_beam(newton=None, tolerance=None):
    """The soft beam (E = 1e5 Pa) without damping at dt = 0.1 s of bench stability."""
    cfg = stability_beam(16, young=1e5, dt=0.1)
    cfg["damping"] = {"mass": 0.0, "stiffness": 0.0}
    cfg["solver"] = {**cfg["solver"], "preconditioner": "async_ldlt",
                     "ldlt": {"rotate": True, "refresh_every": 4, "deterministic": True}}
    if newton is not None:
        cfg["solver"]["newton_iterations"] = newton
    if tolerance is not None:
        cfg["solver"]["newton_tolerance"] = tolerance
    return cfg


def _energy_history(cfg, steps=20):
    with load_scene(cfg, device="cpu") as sim:
        e0 = sim.energy()["total"]
        scale = sim.fem.total_mass * G * float(np.ptp(sim.mesh.points, axis=0).max())
        out, stats = [], []
        for _ in range(steps):
            stats.append(sim.step())
            out.append((sim.energy()["total"] - e0) / scale)
        return np.array(out), stats, sim.positions()


def test_newton_steps_create_no_energy_where_the_single_linearisation_does():
    single, s1, _ = _energy_history(_soft_beam())
    assert single.max() > 0.5  # the paper's step gains half the weight's work and more
    assert all(s.newton_iterations == 1 and s.nonlinear_residual is None for s in s1)
    newton, s3, _ = _energy_history(_soft_beam(newton=3))
    assert newton.max() <= 0.0, newton  # undamped backward Euler: never above the start
    assert np.all(np.diff(newton) <= 1e-9), newton  # and never rising
    assert all(s.newton_iterations == 3 and s.converged for s in s3)
    assert all(0.0 <= s.nonlinear_residual < 1.0 for s in s3)


def test_one_newton_iteration_is_the_papers_step_and_the_tolerance_stops_early():
    _, _, x_default = _energy_history(_soft_beam(), steps=5)
    _, _, x_one = _energy_history(_soft_beam(newton=1), steps=5)
    np.testing.assert_array_equal(x_default, x_one)
    _, stats, _ = _energy_history(_soft_beam(tolerance=0.2), steps=5)
    assert all(s.nonlinear_residual <= 0.2 and s.converged for s in stats)
    most = max(s.newton_iterations for s in stats)
    assert most > 1 and most < 20  # re-linearised, and stopped early
    with pytest.raises(ParameterError, match="newton_iterations"):
        load_scene(_soft_beam(newton=0), device="cpu")
    with pytest.raises(ParameterError, match="newton_tolerance"):
        load_scene(_soft_beam(tolerance=1.5), device="cpu")


# ------------------------------------------------------------------ honest convergence
def _stiff_case():
    """Stiffness ratio 1e6 in one body, Poisson 0.499, dt 0.1, a direct factor (issue 23)."""
    cfg = stability_beam(16, ratio=1e6, poisson=0.499, dt=0.1)
    cfg["solver"] = {**cfg["solver"], "preconditioner": "direct"}
    return cfg


def _true_residual(sim):
    integ = sim.integrator
    A = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef)
    b, x = integ.b.numpy().ravel(), integ.dv.numpy().ravel()
    return np.linalg.norm(b - A @ x) / np.linalg.norm(b)


def test_converged_is_judged_on_the_true_residual_on_the_stiff_case():
    with load_scene(_stiff_case(), device="cpu") as sim:
        s = sim.step()
        true = _true_residual(sim)
        # the recursion claims the tolerance, the solution does not reach it: not converged
        assert s.recursive_residual <= 1e-7 < true and not s.converged
        assert s.residual > 1e-7 and s.residual == pytest.approx(true, rel=3.0)  # rounding-dominated
        assert s.tolerance_unreachable and s.residual_floor > 1e-7
        s = sim.step()  # a step float64 can solve: converged, and the flag is down
        assert s.converged and not s.tolerance_unreachable and s.residual <= 1e-7
        assert _true_residual(sim) <= 1e-7


def test_device_pcg_judges_on_the_true_residual_too():
    """DevicePCG (graph: true; the true residual by device reductions after its loop) and the
    host PCG give the same solve and the same verdict on the stiff case (Jacobi, CPU)."""
    stats = {}
    for graph in (False, True):
        cfg = _stiff_case()
        cfg["solver"] = {**cfg["solver"], "preconditioner": "jacobi", "graph": graph, "max_iterations": 3000}
        with load_scene(cfg, device="cpu") as sim:
            assert isinstance(sim.integrator.cg, DevicePCG) == graph
            first = sim.step()
            true = _true_residual(sim)
            assert first.recursive_residual <= 1e-7 < true and not first.converged and first.tolerance_unreachable
            assert first.residual == pytest.approx(true, rel=0.5)
            second = sim.step()
            assert second.converged and second.residual == pytest.approx(_true_residual(sim), rel=1e-3)
            stats[graph] = [(s.iterations, s.residual, s.recursive_residual, s.residual_floor) for s in (first, second)]
    np.testing.assert_allclose(stats[True], stats[False], rtol=1e-9)


# ------------------------------------------------------------------ state round trip
def test_set_state_round_trip_and_validation():
    cfg = stability_beam(8, dt=0.01)
    with load_scene(cfg, device="cpu") as sim:
        for _ in range(3):
            sim.step()
        rng = np.random.default_rng(1)
        x = sim.mesh.points + 1e-3 * rng.standard_normal(sim.mesh.points.shape)
        v = rng.standard_normal(x.shape)
        sim.set_state(x, v)
        fixed = sim.fem.fixed_nodes
        assert len(fixed) > 0
        np.testing.assert_array_equal(sim.positions(), x)  # fixed nodes too: a prescribed position
        v_expected = v.copy()
        v_expected[fixed] = 0.0  # fixed nodes do not move
        np.testing.assert_array_equal(sim.velocities(), v_expected)
        good_x, good_v = sim.positions(), sim.velocities()
        bad = [(x[:-1], v, "shape"), (x, v[:, :2], "shape"), (np.where(np.arange(len(x))[:, None] == 5, np.nan, x), v,
                                                           "non-finite positions at nodes \\[5\\]"),
               (x, np.full_like(v, np.inf), "non-finite velocities"), ("junk", v, "numeric")]
        for bx, bv, msg in bad:
            with pytest.raises(ValueError, match=msg):
                sim.set_state(bx, bv)
            np.testing.assert_array_equal(sim.positions(), good_x)  # the last good state is kept
            np.testing.assert_array_equal(sim.velocities(), good_v)
        s = sim.step()
        assert s.converged and np.isfinite(sim.positions()).all()
        np.testing.assert_array_equal(sim.positions()[fixed], x[fixed])  # they stay where they were put
        sim.set_state(sim.mesh.points)  # velocities omitted: at rest
        assert not sim.velocities().any()


# ------------------------------------------------------------------ errors
def _materials():
    return [{"id": 0, "young": 1e4, "poisson": 0.3, "density": 1000.0}]


def test_empty_and_unreadable_mesh_files_have_clear_errors(tmp_path):
    empty = tmp_path / "empty.vtu"
    meshio.write(empty, meshio.Mesh(np.zeros((0, 3)), [("tetra", np.zeros((0, 4), int))]))
    no_cells = tmp_path / "no_cells.vtu"
    meshio.write(no_cells, meshio.Mesh(np.zeros((4, 3)), [("tetra", np.zeros((0, 4), int))]))
    zero = tmp_path / "zero.vtu"
    zero.write_bytes(b"")
    junk = tmp_path / "junk.msh"
    junk.write_text("not a mesh")
    cases = [(empty, r"empty mesh \(NumberOfPoints=0"), (no_cells, "empty mesh"),
             (zero, r"the file is empty \(0 bytes\)"),
             (junk, r"could not parse it as ansys or gmsh; it starts with b'not a mesh'")]
    for path, msg in cases:
        with pytest.raises(MeshError, match=msg) as e:
            load_mesh(path)
        assert "concatenate" not in str(e.value) and "SystemExit" not in str(e.value)
        with pytest.raises(MeshError, match=msg):  # the same through a scene
            load_scene({"mesh": {"file": str(path)}, "materials": _materials()}, device="cpu")
    with pytest.raises(MeshError, match="no tetrahedra"):
        validate_mesh(np.zeros((4, 3)), np.zeros((0, 4), int))
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("mesh: {file: [unclosed\n")
    with pytest.raises(ParameterError, match="cannot read scene file .*bad.yaml"):
        load_scene(bad_yaml, device="cpu")
    empty_yaml = tmp_path / "empty.yaml"
    empty_yaml.write_text("")
    with pytest.raises(ParameterError, match=r"does not hold a mapping \(it is empty\)"):
        load_scene(empty_yaml, device="cpu")


# ------------------------------------------------------------------ indentation against Hertz
E_BLOCK, NU_BLOCK, R_BALL, DEPTH = 1.0e4, 0.3, 0.02, 0.8e-3


def _graded(h, n_fine, ratio, n_grow):
    steps = [h] * n_fine + [h * ratio ** (k + 1) for k in range(n_grow)]
    return np.concatenate([[0.0], np.cumsum(steps)])


def boussinesq(X, P, E, nu):
    """Displacement of the half-space z <= 0 under a point force P pushing down at the origin
    (Johnson, Contact Mechanics, eq. 3.20-3.22)."""
    G_ = E / (2.0 * (1.0 + nu))
    r = np.hypot(X[:, 0], X[:, 1])
    d = -X[:, 2]
    rho = np.sqrt(r * r + d * d)
    c = P / (4.0 * np.pi * G_)
    ur = c * (r * d / rho**3 - (1.0 - 2.0 * nu) * r / (rho * (rho + d)))
    u = np.zeros_like(X)
    safe = np.where(r > 0.0, r, 1.0)
    u[:, 0], u[:, 1] = ur * X[:, 0] / safe, ur * X[:, 1] / safe
    u[:, 2] = -c * (d * d / rho**3 + 2.0 * (1.0 - nu) / rho)
    return u


def hertz_force(depth, R=R_BALL, E=E_BLOCK, nu=NU_BLOCK):
    return 4.0 / 3.0 * E / (1.0 - nu * nu) * np.sqrt(R) * depth**1.5


def indent(friction, steps_down=2, hold=1):
    """A rigid sphere (R 20 mm) pressed 0.8 mm into a block (contact radius a = 4 mm) meshed
    with 1.33 mm cells near the contact, graded to 4 a; the block's far boundary (sides,
    bottom) is held at the half-space solution of the Hertz load (Boussinesq), so the block
    stands for a half-space. Quasi-static (dt 1 s, no gravity). Returns the force on the ball."""
    half = _graded(0.004 / 3.0, 4, 1.6, 3)
    xy = np.concatenate([-half[::-1], half[1:]])
    W = half[-1]
    cfg = {"device": "cpu", "mesh": {"generator": "grid", "x": xy.tolist(), "y": xy.tolist(),
                                     "z": (-half[::-1]).tolist()},
           "materials": [{"id": 0, "young": E_BLOCK, "poisson": NU_BLOCK, "density": 1000.0}],
           "damping": {"mass": 0.0, "stiffness": 0.0}, "gravity": [0.0, 0.0, 0.0],
           "fixed": [{"axis": "x", "below": -W}, {"axis": "x", "above": W}, {"axis": "y", "below": -W},
                     {"axis": "y", "above": W}, {"axis": "z", "below": -W}],
           "time": {"dt": 1.0}, "solver": {"preconditioner": "direct", "tolerance": 1e-10, "max_iterations": 200},
           "instruments": [{"name": "ball", "shape": "sphere", "radius": R_BALL,
                            "pose": {"position": [0.0, 0.0, R_BALL]}}],
           "contact": {"distance": 2e-4, "friction": friction, "max_iterations": 1000, "tolerance": 1e-10}}
    with load_scene(cfg) as sim:
        X = sim.mesh.points
        x0 = X.copy()
        fixed = sim.fem.fixed_nodes
        x0[fixed] += boussinesq(X[fixed], hertz_force(DEPTH), E_BLOCK, NU_BLOCK)
        sim.set_state(x0)
        for k in range(steps_down + hold):
            d = DEPTH * min(k + 1, steps_down) / steps_down
            sim.set_instrument_pose("ball", [0.0, 0.0, R_BALL - d], [0, 0, 0, 1])
            s = sim.step()
            assert s.extra["compliance"] == "preconditioner"  # never the diagonal fallback
        c = sim.contact.contacts
        on = c["lambda_n"] > 0.0
        t = c["force"][on] - np.einsum("ij,ij->i", c["force"][on], c["normal"][on])[:, None] * c["normal"][on]
        slip_ratio = np.linalg.norm(t, axis=1) / c["lambda_n"][on]
        return sim.instrument_wrench("ball")[0], slip_ratio


@pytest.mark.parametrize("friction", [0.0, 0.2, 5.0])
def test_sphere_indenting_a_block_matches_hertz_frictionless_and_stuck(friction):
    """Hertz for the frictionless case; with friction the exact (Spence) load differs from it by
    a few percent at Poisson 0.3, so every case must be within 10 %. Friction 5 sticks every
    contact (full stick). Before the fix of contact.compliance.positive_definite, friction made the
    compliance fall back to its diagonal: 13.8 x Hertz."""
    F, slip = indent(friction)
    assert F[2] == pytest.approx(hertz_force(DEPTH), rel=0.10)
    assert abs(F[0]) < 1e-3 * F[2] and abs(F[1]) < 1e-3 * F[2]  # the symmetric mesh: straight up
    if friction == 5.0:  # stuck: inside the cone (a contact or two at the rim may slide)
        assert len(slip) > 20 and np.mean(slip < 0.5 * friction) > 0.9
    if friction == 0.0:
        assert slip.max() < 1e-12


# ------------------------------------------------------------------ known contact limits (for contact.py)
@pytest.mark.xfail(strict=True, reason="face contacts of a capsule parallel to a face alternate between two "
                                       "sets every step (contact detection); see test_contact's wrench test")
def test_capsule_parallel_to_a_face_comes_to_rest():
    cfg = scene(mesh={"generator": "beam", "n_long": 5, "n_cross": 5, "spacing": 0.005},
                materials=[{"id": 0, "young": 2.0e4, "poisson": 0.3, "density": 1000.0}],
                damping={"mass": 2.0, "stiffness": 0.01}, fixed={"axis": "z", "below": -0.01},
                instruments=[{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05}],
                contact={"tolerance": 1e-10})
    q = [0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)]
    tip = np.array([-0.006, 0.001, 0.0145])
    forces = []
    with load_scene(cfg) as sim:
        for i in range(150):
            sim.set_instrument_pose("probe", tip - [0.0, 0.0, min(i, 20) / 20 * 0.002], q)
            sim.step()
            forces.append(sim.instrument_wrench("probe")[0])
    assert np.linalg.norm(forces[-1] - forces[-2]) <= 0.01 * np.linalg.norm(forces[-1])


@pytest.mark.xfail(strict=True, reason="a node falling level with a corner edge of the other side gets a "
                                       "horizontal self-contact normal, which misses the fall (contact detection)")
def test_a_corner_node_falling_past_a_corner_edge_is_caught(tmp_path):
    m = beam_mesh(6, 4, spacing=0.01)  # mirrored split
    cen = m.centroids()
    slot = (np.abs(cen[:, 2]) < 0.005) & (cen[:, 0] > 0.01)
    path = tmp_path / "u.vtu"
    save_mesh(validate_mesh(m.points, m.tets[~slot]), path)
    cfg = scene(mesh={"file": str(path)}, materials=[{"id": 0, "young": 5.0e3, "poisson": 0.3, "density": 1000.0}],
                fixed=[{"axis": "z", "below": -0.005}, {"axis": "x", "below": 0.0}], contact={"self_collision": True})
    with load_scene(cfg) as sim:
        pts, tets = sim.mesh.points, sim.mesh.tets
        lower = tets[(pts[tets][:, :, 2] <= -0.005 + 1e-9).all(axis=1)]
        upper = pts[:, 2] > 0.004
        for _ in range(10):
            sim.step()
            x = sim.positions()
            assert not inside_any_tet(x, lower, x[upper]).any()
