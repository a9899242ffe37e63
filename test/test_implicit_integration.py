"""Backward Euler + CG: analytic deflection, residuals, energy, reset, parameter checks."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from soft_tissue_sim import ParameterError, load_scene


def beam_scene(n_long, n_cross, preconditioner="jacobi", dt=0.01, young=1e5, poisson=0.3, damping=(0.5, 0.01),
               tolerance=1e-7, length=None, width=None, max_iterations=3000, **extra):
    mesh = {"generator": "beam", "n_long": n_long, "n_cross": n_cross}
    if length is not None:
        mesh.update(length=length, width=width)
    else:
        mesh["spacing"] = 0.01
    cfg = {
        "name": f"beam{n_cross}x{n_cross}x{n_long}",
        "device": "cpu",
        "mesh": mesh,
        "materials": [{"id": 0, "young": young, "poisson": poisson, "density": 1000.0}],
        "damping": {"mass": damping[0], "stiffness": damping[1]},
        "gravity": [0.0, 0.0, -9.81],
        "fixed": {"axis": "x", "below": 0.0},
        "time": {"dt": dt},
        "solver": {"preconditioner": preconditioner, "tolerance": tolerance, "max_iterations": max_iterations,
                   "ldlt": {"deterministic": True}},
    }
    cfg.update(extra)
    return cfg


def test_cantilever_tip_deflection_converges_to_euler_bernoulli():
    """Static sag of a clamped beam under its weight vs q L^4 / (8 E I), refined 3 times.

    A few backward Euler steps with a huge dt from rest reach the static equilibrium.
    Linear tets are too stiff in bending, so the error must fall with refinement.
    """
    L, a, E, rho, g = 0.4, 0.04, 2e7, 1000.0, 9.81
    q = rho * g * a * a
    w_eb = q * L**4 / (8 * E * a**4 / 12)
    ratios = []
    for n_cross, n_long in ((3, 21), (5, 41), (9, 81)):
        # 1e-8: with dt = 100 s float64 reaches about 1e-9 on the finest beam's first step (the
        # true residual of a 1e-10 solve is 1.4e-10, its recursion claims 1e-20)
        cfg = beam_scene(n_long, n_cross, preconditioner="direct", dt=100.0, young=E, poisson=0.0,
                         damping=(0.0, 0.0), tolerance=1e-8, length=L, width=a)
        with load_scene(cfg) as sim:
            for _ in range(3):
                s = sim.step()
                assert s.converged
            x, X = sim.positions(), sim.mesh.points
            tip = X[:, 0] > L - 1e-9
            ratios.append(-(x - X)[tip, 2].mean() / w_eb)
    errors = [abs(1 - r) for r in ratios]
    assert errors[0] > errors[1] > errors[2], ratios
    assert errors[2] < 0.10, ratios
    assert all(r < 1.0 for r in ratios)  # linear tets are stiffer than the beam


@pytest.mark.parametrize("mass", ["lumped", "consistent"])
def test_cg_matches_a_direct_solve_of_the_assembled_system(mass):
    cfg = beam_scene(16, 3, preconditioner="none", tolerance=1e-9, mass=mass)
    with load_scene(cfg) as sim:
        for _ in range(5):  # get some motion so that rotations and damping terms matter
            sim.step()
        integ = sim.integrator
        integ.build()
        A = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef)
        b = integ.b.numpy().ravel()
        res = integ.cg.solve(integ.matvec, integ.b, integ.dv, integ.preconditioner)
        x_cg = integ.dv.numpy().ravel()
        x_direct = spla.spsolve(A, b)
        assert res.converged and res.iterations > 5
        assert np.linalg.norm(A @ x_cg - b) <= 1.01e-9 * np.linalg.norm(b)
        assert np.linalg.norm(x_cg - x_direct) <= 1e-6 * np.linalg.norm(x_direct)


@pytest.mark.parametrize("device_scalars", [False, True])
def test_a_warm_start_reaches_the_tolerance_from_its_guess_and_drops_a_bad_one(device_scalars):
    """PCG's warm_start: from a guess near the solution fewer iterations to the same relative
    tolerance; from a guess whose residual is not below ||b|| (far, or NaN) the cold solve
    exactly (x = 0, r = b), for the host-scalar and the device-scalar PCG alike."""
    from soft_tissue_sim.cg import DevicePCG

    tol = 1e-9
    with load_scene(beam_scene(16, 3, preconditioner="jacobi", tolerance=tol)) as sim:
        for _ in range(5):
            sim.step()
        integ = sim.integrator
        integ.build()
        integ.preconditioner.begin_step(integ)
        cg = DevicePCG(sim.fem.n_nodes, "cpu", tol, 3000) if device_scalars else integ.cg
        A = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef)
        b = integ.b.numpy().ravel()

        def solve(guess, warm):
            cg.warm_start = warm
            integ.dv.assign(guess)
            res = cg.solve(integ.matvec, integ.b, integ.dv, integ.preconditioner)
            x = integ.dv.numpy().copy()
            assert res.converged and np.linalg.norm(A @ x.ravel() - b) <= 1.01 * tol * np.linalg.norm(b)
            return res, x

        cold, x_cold = solve(np.full((sim.fem.n_nodes, 3), 7.0), warm=False)  # the guess is ignored
        warm, _ = solve(0.99 * x_cold, warm=True)  # the error a hundredth of the cold start's
        assert cold.iterations > 5 and warm.iterations < cold.iterations
        for bad in (np.full_like(x_cold, np.nan), 1e3 * (1.0 + np.abs(x_cold))):
            res, x = solve(bad, warm=True)
            assert res.iterations == cold.iterations
            np.testing.assert_array_equal(x, x_cold)


@pytest.mark.parametrize("pre", ["none", "jacobi"])
def test_step_reports_the_residual_it_reached(pre):
    cfg = beam_scene(12, 3, preconditioner=pre, tolerance=1e-6)
    with load_scene(cfg) as sim:
        s = sim.step()
        assert s.converged and 0 < s.iterations < 500 and s.residual <= 1e-6
        assert s.total_ms >= s.solve_ms > 0 and s.build_ms > 0
        assert s.preconditioner == pre


def test_jacobi_needs_fewer_iterations_than_plain_cg_on_a_heterogeneous_body():
    stiff = beam_scene(20, 3, preconditioner="none",
                       materials=[{"id": 0, "young": 1e4, "poisson": 0.3, "density": 1000.0}])
    it = {}
    for pre in ("none", "jacobi"):
        cfg = dict(stiff, solver={**stiff["solver"], "preconditioner": pre})
        with load_scene(cfg) as sim:
            it[pre] = sum(sim.step().iterations for _ in range(3))
    assert it["jacobi"] < it["none"]


def test_damped_energy_decays_and_stays_finite():
    cfg = beam_scene(20, 3, preconditioner="jacobi", damping=(1.0, 0.02), young=5e4)
    with load_scene(cfg) as sim:
        energies = [sim.energy()["total"]]
        for k in range(300):
            s = sim.step()
            assert s.converged
            if k % 10 == 9:
                energies.append(sim.energy()["total"])
        assert np.all(np.isfinite(sim.positions())) and np.all(np.isfinite(sim.velocities()))
        e = np.array(energies)
        # each sample no higher than the previous one (up to round-off), and a clear overall loss
        scale = abs(e).max()
        assert np.all(np.diff(e) <= 1e-9 * scale), e
        assert e[-1] < e[0] - 1e-3 * scale
        # at rest at the end: kinetic energy is a tiny fraction of what was lost
        assert sim.energy()["kinetic"] < 1e-3 * (e[0] - e[-1])


def test_reset_restores_the_initial_state_exactly():
    cfg = beam_scene(10, 3, preconditioner="jacobi")
    with load_scene(cfg) as sim:
        x0, v0 = sim.positions(), sim.velocities()
        first = [sim.step().residual for _ in range(3)]
        x3 = sim.positions()
        assert not np.array_equal(x0, x3)
        sim.reset()
        np.testing.assert_array_equal(sim.positions(), x0)
        np.testing.assert_array_equal(sim.velocities(), v0)
        assert sim.step_count == 0 and sim.time == 0.0
        again = [sim.step().residual for _ in range(3)]
        assert again == first
        np.testing.assert_array_equal(sim.positions(), x3)


def test_fixed_nodes_do_not_move():
    cfg = beam_scene(10, 3)
    with load_scene(cfg) as sim:
        fixed = sim.fem.fixed_nodes
        assert len(fixed) == 9
        X = sim.mesh.points.copy()
        for _ in range(5):
            sim.step()
        np.testing.assert_array_equal(sim.positions()[fixed], X[fixed])
        assert np.abs(sim.positions() - X).max() > 1e-5


@pytest.mark.parametrize(
    "change, msg",
    [
        ({"time": {"dt": 0.0}}, "dt"),
        ({"time": {"dt": -0.01}}, "dt"),
        ({"time": {"dt": float("nan")}}, "dt"),
        ({"materials": [{"id": 0, "young": -1.0, "poisson": 0.3, "density": 1000.0}]}, "Young"),
        ({"materials": [{"id": 0, "young": 1e5, "poisson": 0.5, "density": 1000.0}]}, "Poisson"),
        ({"materials": [{"id": 0, "young": 1e5, "poisson": 0.3}]}, "density"),
        ({"gravity": [0.0, float("nan"), 0.0]}, "gravity"),
        ({"damping": {"mass": -1.0}}, "damping"),
        ({"solver": {"preconditioner": "magic"}}, "preconditioner"),
        ({"solver": {"tolerance": 0.0}}, "tolerance"),
        ({"solver": {"warm_start": "yes"}}, "warm_start"),
        ({"device": "tpu"}, "device"),
        ({"viscosity": 3}, "unknown scene keys"),
        ({"fixed": {"nodes": [10_000]}}, "out of range"),
    ],
)
def test_impossible_scene_parameters_raise_clear_errors(change, msg):
    cfg = beam_scene(4, 2)
    cfg.update(change)
    with pytest.raises((ParameterError, ValueError), match=msg):
        load_scene(cfg)


def test_missing_scene_file_is_named():
    with pytest.raises(FileNotFoundError, match="no_such_scene.yaml"):
        load_scene("no_such_scene.yaml")


@pytest.mark.parametrize("name", ["default.yaml", "beam_1200.yaml", "test_small.yaml", "brain_resection.yaml"])
def test_shipped_scenes_load_from_yaml_and_step(name):
    with load_scene(name, device="cpu") as sim:
        assert sim.materials.materials[0].young > 0  # YAML "1.0e6" read as a number
        s = sim.step()
        assert s.converged and np.all(np.isfinite(sim.positions()))
        cfg = sim.config  # nothing built that the scene does not name
        named_contact = bool(cfg.get("instruments") or cfg.get("obstacles") or (cfg.get("contact") or {}).get("self_collision"))
        assert (sim.contact is not None) == named_contact
        assert (sim.cutting is not None) == bool(cfg.get("cutting"))


def test_default_beam_1000_damped_steps_lose_energy_and_stay_finite():
    with load_scene("beam_2000.yaml", device="cpu", overrides={"solver": {"ldlt": {"refresh_every": 5}}}) as sim:
        e0 = sim.energy()["total"]
        peak_ke = 0.0
        for _ in range(1000):
            s = sim.step()
            assert s.converged
            peak_ke = max(peak_ke, sim.energy()["kinetic"]) if s.step % 50 == 0 else peak_ke
        e = sim.energy()
        assert np.all(np.isfinite(sim.positions()))
        assert e["total"] < e0 and peak_ke > 0
        assert e["kinetic"] < peak_ke  # motion is being damped out


def test_a_diverging_step_is_rolled_back_and_the_simulation_carries_on():
    with load_scene(beam_scene(10, 3, preconditioner="async_ldlt")) as sim:
        for _ in range(3):
            sim.step()
        x_good, v_good, t_good = sim.positions(), sim.velocities(), sim.time
        f = np.zeros((sim.mesh.n_nodes, 3))
        f[-1, 2] = np.nan  # a broken external load
        sim.integrator.f_ext.assign(f)
        s = sim.step()
        assert s.extra["rolled_back"] and not s.converged and sim.rollbacks == 1
        assert not np.any(sim.integrator.dv.numpy())  # the failed solve is no guess for the next
        np.testing.assert_array_equal(sim.positions(), x_good)
        np.testing.assert_array_equal(sim.velocities(), v_good)
        assert sim.time == t_good and sim.step_count == 3
        sim.integrator.f_ext.zero_()
        s = sim.step()
        assert s.converged and np.all(np.isfinite(sim.positions())) and sim.step_count == 4


def test_runaway_energy_is_rolled_back_and_the_step_retried():
    with load_scene(beam_scene(10, 3, preconditioner="async_ldlt")) as sim:
        for _ in range(3):
            sim.step()
        real_step = sim.integrator.step
        calls = []

        def kicked_step():
            s = real_step()
            if not calls:  # the first attempt blows up: a velocity kick of 1 km/s on one node
                v = sim.integrator.v.numpy()
                v[-1] += 1000.0
                sim.integrator.v.assign(v)
            calls.append(s)
            return s

        sim.integrator.step = kicked_step
        s = sim.step()
        assert s.extra["rolled_back"] and "runaway energy" in s.extra["guard"]
        assert s.extra["remedy"] == "fresh factor" and s.converged and sim.rollbacks == 1
        assert np.abs(sim.velocities()).max() < 10.0 and sim.step_count == 4
        sim.integrator.step = real_step
        assert "rolled_back" not in sim.step().extra


def test_a_step_that_keeps_failing_keeps_the_last_good_state():
    with load_scene(beam_scene(10, 3, preconditioner="async_ldlt")) as sim:
        sim.step()
        x_good, n_good = sim.positions(), sim.step_count
        f = np.zeros((sim.mesh.n_nodes, 3))
        f[0, 0] = np.inf
        sim.integrator.f_ext.assign(f)
        s = sim.step()
        assert not s.converged and s.extra["remedy"].startswith("none")
        np.testing.assert_array_equal(sim.positions(), x_good)
        assert sim.step_count == n_good and sim.integrator.dt == 0.01


def test_a_failing_second_half_step_goes_back_to_the_step_start_not_the_half_step():
    """The step's start is copied by each build (in its graph); the retries' builds copy their
    own starts, so the state a failed step goes back to is kept aside at the first failure:
    a first half step that holds and a second that blows up leave the last good state, not the
    half step's."""
    with load_scene(beam_scene(10, 3, preconditioner="async_ldlt")) as sim:
        for _ in range(3):
            sim.step()
        x_good, v_good = sim.positions(), sim.velocities()
        real_step = sim.integrator.step
        calls = []

        def step():
            s = real_step()
            calls.append(s)
            if len(calls) in (1, 2, 4):  # the step, its fresh-factor retry, the second half step
                v = sim.integrator.v.numpy()
                v[-1] += 1000.0
                sim.integrator.v.assign(v)
            return s

        sim.integrator.step = step
        s = sim.step()
        assert len(calls) == 4 and s.extra["remedy"].startswith("none")
        np.testing.assert_array_equal(sim.positions(), x_good)
        np.testing.assert_array_equal(sim.velocities(), v_good)


def test_a_step_runs_its_host_blas_on_one_thread_unless_told_otherwise(monkeypatch):
    """``solver.blas_threads``: one (default) holds the one-thread BLAS scope during the step
    and leaves it after; default does not enter it; anything else is refused."""
    from soft_tissue_sim import blas_threads, load_scene
    from soft_tissue_sim.material import ParameterError
    from soft_tissue_sim.scene import Simulation

    seen = []
    real = Simulation._free_motion

    def spy(self):
        seen.append(blas_threads._inside)
        return real(self)

    monkeypatch.setattr(Simulation, "_free_motion", spy)
    for mode, inside in (("one", 1), ("default", 0)):
        with load_scene("test_small.yaml", overrides={"solver": {"blas_threads": mode}}) as sim:
            seen.clear()
            sim.step()
            assert seen == [inside] and blas_threads._inside == 0
    with pytest.raises(ParameterError, match="blas_threads"):
        load_scene("test_small.yaml", overrides={"solver": {"blas_threads": 2}})


def test_the_guard_reuses_the_kinetic_energy_it_read_while_the_state_is_unchanged(monkeypatch):
    """A step's "before" energy is the last guard's reading of the same state; after any change
    of the state from outside a step it is measured again."""
    with load_scene(beam_scene(6, 3, preconditioner="async_ldlt")) as sim:
        calls = []
        real = sim._kinetic_energy
        monkeypatch.setattr(sim, "_kinetic_energy", lambda: calls.append(1) or real())
        sim.step()
        assert len(calls) == 1  # nothing read yet: measured
        sim.step()
        assert len(calls) == 1  # the first step's guard read this state
        sim.set_state(sim.positions(), sim.velocities())
        sim.step()
        assert len(calls) == 2
        sim.integrator.set_state(sim.positions(), sim.velocities())  # new arrays behind the simulation's back
        sim.step()
        assert len(calls) == 3
        x = sim.integrator.x
        sim.step()
        assert len(calls) == 3 and sim.integrator.x is x  # the step kept the integrator's arrays


def test_a_rollback_restores_the_state_into_the_same_arrays():
    with load_scene(beam_scene(10, 3, preconditioner="async_ldlt")) as sim:
        for _ in range(2):
            sim.step()
        x, v = sim.integrator.x, sim.integrator.v
        real_step = sim.integrator.step
        state = []

        def kicked_step():
            if not state:
                state.append(sim.positions())
                s = real_step()
                vv = sim.integrator.v.numpy()
                vv[-1] += 1000.0
                sim.integrator.v.assign(vv)
                return s
            return real_step()

        sim.integrator.step = kicked_step
        s = sim.step()
        assert s.extra["rolled_back"]
        assert sim.integrator.x is x and sim.integrator.v is v  # graphs captured on them stay valid
        assert np.abs(sim.velocities()).max() < 10.0


def test_a_device_solve_reads_the_guard_with_its_result(monkeypatch):
    """With the PCG's scalars on the device (a device factor), the step launches the divergence
    guard after the update and reads it in the same wait: the guard's values are those of the new
    state, and the simulation does not launch the guard again to judge the step."""
    cfg = beam_scene(6, 3, preconditioner="async_ldlt")
    cfg["solver"]["ldlt"] = {"backend": "dense"}
    with load_scene(cfg) as sim:
        sim.step()
        integ = sim.integrator
        assert hasattr(integ.cg, "launch")
        launches = []
        real = integ.launch_guard
        monkeypatch.setattr(integ, "launch_guard", lambda: launches.append(1) or real())
        s = sim.step()
        assert len(launches) == 1 and integ.guard_reading is not None and s.converged
        ke, nonfinite = integ.guard_reading
        v, mass = sim.velocities(), integ.fem.lumped_mass.numpy()
        assert ke == pytest.approx(0.5 * np.sum(mass * np.sum(v * v, axis=1)), rel=1e-12)
        assert nonfinite == 0.0


def test_the_preconditioner_takes_the_node_rotations_build_launched_and_recomputes_stale_ones(monkeypatch):
    """With a device factor the integrator's build launches the node rotations of eq. (2) and the
    preconditioner's begin_step uses them without launching them again; after element rotations
    changed outside a build (update_rotations) they are launched anew."""
    ov = {"solver": {"preconditioner": "async_ldlt", "ldlt": {"backend": "dense", "deterministic": True}}}
    with load_scene("test_small.yaml", overrides=ov) as sim:
        integ, fem = sim.integrator, sim.fem
        assert integ.node_rotations_in_build
        sim.step()
        calls = []
        real = fem.update_node_rotations
        monkeypatch.setattr(fem, "update_node_rotations", lambda: calls.append(1) or real())
        integ.build()
        assert len(calls) == 1 and fem.node_rotations_current
        sim.preconditioner.begin_step(integ)
        assert len(calls) == 1  # taken from the build
        R_built = fem.current_node_rotations().numpy().copy()
        x = integ.x.numpy()
        x[:, 0] += 0.3 * x[:, 2]  # a shear: other element rotations
        integ.x.assign(x)
        fem.update_rotations(integ.x)
        assert not fem.node_rotations_current
        sim.preconditioner.begin_step(integ)
        assert len(calls) == 2  # stale: launched again
        assert np.abs(fem.current_node_rotations().numpy() - R_built).max() > 1e-3
