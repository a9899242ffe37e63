"""bench targets: the rows of the cut's host cost, from the resection run it already makes."""

import numpy as np
import pytest

from soft_tissue_sim.bench import brain, targets


SHARES = {"plan_ms": 0.1, "apply_ms": 0.2, "correction_ms": 0.3, "surface_ms": 0.25, "debris_ms": 0.05}


def _rows(cut_ms, modified):
    return [{"step": k + 1, "wall_ms": 10.0 + c, "iterations": 4, "rolled_back": False, "modified": m,
             "cut_ms": c, **{p: f * c if m else 0.0 for p, f in SHARES.items()}}
            for k, (c, m) in enumerate(zip(cut_ms, modified))]


def test_the_cut_rows_are_the_median_and_p99_over_the_steps_with_a_modification():
    rng = np.random.default_rng(0)
    cut = rng.uniform(0.1, 30.0, 300)
    mod = rng.uniform(size=300) < 0.3
    rows = targets.cut_rows(_rows(cut, mod))
    by = {r["name"]: r for r in rows}
    assert set(by) == {"brain_cut_ms_median", "brain_cut_ms_p99"}
    med, p99 = by["brain_cut_ms_median"], by["brain_cut_ms_p99"]
    assert med["value"] == pytest.approx(np.median(cut[mod])) and med["goal"] == 5.0
    assert p99["value"] == pytest.approx(np.percentile(cut[mod], 99)) and p99["goal"] == 20.0
    for r in (med, p99):
        assert r["unit"] == "ms" and r["goal_relation"] == "<=" and r["met"] == (r["value"] <= r["goal"])
        assert f"{mod.sum()} steps with a modification" in r["note"]
        # the parts' medians, and the rest (here 10 % of each cut) named
        for name, share in (("planning", 0.1), ("FEM, state and identities", 0.2), ("correction", 0.3),
                            ("contact surface", 0.25), ("debris", 0.05), ("plans that changed nothing)", 0.1)):
            assert f"{name} {np.median(share * cut[mod]):.2f}" in r["note"]
    none = targets.cut_rows(_rows([1.0, 2.0], [False, False]))
    assert [r["value"] for r in none] == [None, None] and all(r["met"] is None for r in none)


def test_the_resection_rows_include_the_cut_rows(monkeypatch):
    """brain_resection_rows takes the cut rows from the same run (no second run)."""
    calls = []

    def fake_run(device, progress=False, ldlt=None):
        calls.append(device)
        rows = _rows([0.0, 4.0, 0.0, 6.0, 8.0], [False, True, False, True, True])
        graphs = {"after the solve": {"captures": 4, "replays": 655, "plain": 6}}
        return rows, [{}] * 3, True, True, 0, 0, {"inverted_tets_end": 0, "step_graphs": graphs}

    monkeypatch.setattr(brain, "run", fake_run)
    rows = {r["name"]: r for r in targets.brain_resection_rows("cpu")}
    assert calls == ["cpu"]
    assert "the launches after the solve captured 4, replayed 655, plain 6" in rows["brain_resection_step_median_ms"]["note"]
    assert rows["brain_cut_ms_median"]["value"] == 6.0 and rows["brain_cut_ms_median"]["met"] is False
    assert rows["brain_cut_ms_p99"]["value"] == pytest.approx(np.percentile([4.0, 6.0, 8.0], 99))
    assert rows["brain_cut_ms_p99"]["goal"] == rows["brain_resection_step_p99_ms"]["goal"] == 20.0
    assert "brain_resection_step_median_ms" in rows and "brain_resection_fps" in rows


def test_the_resection_note_splits_the_steps_by_kind():
    """Modified steps, the steps right after one (not modified themselves), the other steps of
    more than 32 contacts, the rest: each kind's median, p99 and count."""
    mod = [False, True, False, True, True, False, False, False]
    contacts = [40, 50, 40, 0, 0, 0, 33, 5]
    wall = [1.0, 20.0, 9.0, 30.0, 40.0, 7.0, 5.0, 2.0]
    rows = [{"wall_ms": w, "modified": m, "contacts": c} for w, m, c in zip(wall, mod, contacts)]
    note = targets.resection_split(rows)
    assert f"with a modification {np.median([20.0, 30.0, 40.0]):.2f} / {np.percentile([20.0, 30.0, 40.0], 99):.2f} (3)" in note
    assert f"right after one {np.median([9.0, 7.0]):.2f} / {np.percentile([9.0, 7.0], 99):.2f} (2)" in note
    assert "other steps of more than 32 contacts 3.00 / 4.96 (2)" in note  # steps 0 and 6
    assert "the others 2.00 / 2.00 (1)" in note


def test_the_cut_beam_note_splits_the_steps_by_their_place_around_the_cuts():
    """Steps 1, 4, 7 cut; 2, 5, 8 follow a cut; the others are between cuts."""
    stats = []
    for i in range(9):
        cut, after = i % 3 == 1, i % 3 == 2
        stats.append({"total_ms": 1.0 + 2.0 * after, "solve_ms": 0.5 + after, "tets_changed": 4 if cut else 0,
                      **({"cut_ms": 10.0, "plan_ms": 3.0, "apply_ms": 2.0, "correction_ms": 4.0, "debris_ms": 0.5}
                         if cut else {})})
    note = targets.beam_split(stats)
    assert note.startswith("steps between cuts 1.00 (solve 0.50), a cut's step 11.00 of which its cutting phase 10.00")
    assert "(planning 3.00, FEM, state and identities 2.00, correction 4.00, debris 0.50)" in note
    assert note.endswith("the step after a cut 3.00 (solve 1.50)")


def test_ldlt_settings_reach_every_brain_row(monkeypatch):
    """--ldlt KEY=VALUE: values read as JSON where they parse; laid over the brain scene's
    solver.ldlt in the rows' scene and passed to the resection's run; a malformed one refused."""
    assert targets.parse_ldlt(["reserve_sms=48", "apply_precision=float64", "rotate=false"]) == {
        "reserve_sms": 48, "apply_precision": "float64", "rotate": False}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        targets.parse_ldlt(["reserve_sms"])
    base = targets._brain(contact=True)["solver"]["ldlt"]
    monkeypatch.setattr(targets, "LDLT", {"reserve_sms": 48, "device_refresh_iterations": 8})
    cfg = targets._brain(contact=True)
    assert cfg["solver"]["ldlt"] == {**base, "reserve_sms": 48, "device_refresh_iterations": 8}
    assert "device_refresh_iterations" in base and base["device_refresh_iterations"] != 8
    seen = {}

    def fake_run(device, progress=False, ldlt=None):
        seen["ldlt"] = ldlt
        rows = _rows([0.0, 4.0], [False, True])
        graphs = {"after the solve": {"captures": 0, "replays": 0, "plain": 2}}
        return rows, [{}], True, True, 0, 0, {"inverted_tets_end": 0, "step_graphs": graphs}

    monkeypatch.setattr(brain, "run", fake_run)
    targets.brain_resection_rows("cpu")
    assert seen["ldlt"] == {"reserve_sms": 48, "device_refresh_iterations": 8}


def test_the_resection_run_lays_ldlt_settings_over_the_scene(monkeypatch):
    """brain.run(ldlt=...) loads the scene with those solver.ldlt settings over its own."""
    loaded = {}

    def fake_load(scene, device=None, overrides=None):
        loaded["ldlt"] = overrides["solver"]["ldlt"]
        raise RuntimeError("stop here")

    monkeypatch.setattr(brain, "load_scene", fake_load)
    with pytest.raises(RuntimeError, match="stop here"):
        brain.run("cpu", ldlt={"reserve_sms": 48})
    assert loaded["ldlt"]["reserve_sms"] == 48 and loaded["ldlt"]["backend"] == "auto"
    assert loaded["ldlt"]["device_refresh_iterations"] == 4  # the scene's own kept
