"""``bench lcp``: the LCPs recorded from a scene are solved again by the host and by the device
kernel (here Warp's CPU backend), which agree; the recording leaves the host solver as it was."""

import json

import numpy as np
import pytest

from soft_tissue_sim.bench import lcp
from soft_tissue_sim.contact.device_lcp import BIG
from soft_tissue_sim.contact.pgs import PGS


def test_the_default_scenes_sets_are_recorded_and_solved_alike(tmp_path):
    assert lcp.main(["--device", "cpu", "--steps", "200", "--every", "3", "--large", "0", "--trajectory", "0",
                     "--out", str(tmp_path)]) == 0
    f = json.load(open(tmp_path / "lcp_cpu.json"))["figures"]
    d = f["default"]
    assert d["sets"] > 5 and d["rows_median"] >= 3 and d["frictional"] == d["sets"]  # the scene's friction
    assert d["iterations_mean"] > 1.0 and d["host_ms_mean"] > 0.0 and d["device_ms_mean"] > 0.0
    assert d["lambda_max_relative_difference"] <= 1e-9
    assert "resection" not in f
    # the host with the friction finish on the same (frictional) sets: never more sets above the
    # tolerance, fewer iterations
    g = d["friction_finish"]
    assert g["above_tolerance"] <= d["above_tolerance"] and g["iterations_mean"] <= d["iterations_mean"]
    assert g["host_ms_mean"] > 0.0 and g["device_ms_mean"] > 0.0
    assert g["displacement_max_difference_m"] <= 1e-12  # the device's finish is the host's (Warp's CPU backend)


def test_a_large_set_goes_to_the_wide_buffers_and_a_bad_device_solve_shows():
    rng = np.random.default_rng(4)
    m = 60
    B = rng.standard_normal((m, m // 2))
    W = B @ B.T / m + 1e-4 * np.eye(m)  # nearly repeated rows: the active-set finish runs
    one = np.arange(m, dtype=np.int32)
    problem = (W, rng.standard_normal(m) * 1e-3, one, np.ones(m, np.int32), np.zeros(m), np.zeros(m), 1e-10, False,
               200)
    f = lcp.compare([problem], BIG, "cpu")
    assert f["sets"] == 1 and f["rows_median"] == m and f["frictional"] == 0 and f["device_buffer_rows"] == BIG
    assert f["above_tolerance"] == 0 and "friction_finish" not in f  # no friction: no finish to compare
    assert f["lambda_max_relative_difference"] <= 1e-9
    # a device solve that differs from the host's is reported as such
    bad = (-W,) + problem[1:]
    assert lcp.compare([bad], BIG, "cpu")["lambda_max_relative_difference"] > 0.5


def test_recording_restores_the_host_solver():
    solve = PGS.solve
    with pytest.raises(RuntimeError):
        with lcp.recording(lambda m: True) as sets:
            assert PGS.solve is not solve
            PGS().solve(np.eye(2), np.array([-1.0, 1.0]), np.arange(2, dtype=np.int32), np.ones(2, np.int32),
                        np.zeros(2), 50, 1e-12, False, np.zeros(2))
            raise RuntimeError("stop")
    assert PGS.solve is solve and len(sets) == 1 and sets[0][1].tolist() == [-1.0, 1.0]


def test_the_trajectory_compares_each_lcp_setting_with_the_converged_one():
    """The default scene's trajectory (its first 160 steps: the scalpel lowered and pressed) with
    each setting: the converged run is its own reference (no error), the sweeps alone and the
    finished runs have fewer iterations and an error of their own, the finish fewer iterations
    and steps above the tolerance than the sweeps alone."""
    f = lcp.trajectory("cpu", 160)
    ref, shipped, finish = f["converged"], f["sweeps"], f["friction_finish"]
    assert f["steps"] == 160
    assert ref["wrench_error_p99"] == 0.0 and ref["positions_max_error_m"] == 0.0
    assert ref["iterations_mean"] > shipped["iterations_mean"] > finish["iterations_mean"] > 1.0
    assert finish["above_tolerance_fraction"] <= shipped["above_tolerance_fraction"]
    assert 0.0 < shipped["wrench_error_median"] < 0.1 and shipped["positions_max_error_m"] > 0.0
    assert all(g["step_ms_median"] > 0.0 for g in (ref, shipped, finish))
