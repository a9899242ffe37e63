"""The brain bench's closed-loop surgeon: the attachment cut and the tumour-sparing bite
(topology and geometry only, on the rest state: no time stepping)."""

import numpy as np
import pytest

from soft_tissue_sim.scenarios.brain import attachment_cut, spare_tumour_bite, specimen_tets, tumour_freed
from soft_tissue_sim.scene import load_scene


@pytest.fixture(scope="module")
def sim():
    s = load_scene("brain_resection.yaml", device="cpu")
    yield s
    s.close()


def test_attachment_cut_frees_without_touching_the_tumour(sim):
    import scipy.sparse as sps
    from scipy.sparse.csgraph import connected_components

    assert not tumour_freed(sim)
    cut = attachment_cut(sim)
    m = sim.mesh
    assert len(cut) > 0 and not np.any(m.material_ids[cut] == 1)
    keep = np.ones(m.n_tets, bool)
    keep[cut] = False
    T = m.tets[keep]
    g = sps.coo_matrix((np.ones(16 * len(T)), (np.repeat(T, 4, axis=1).ravel(), np.tile(T, (1, 4)).ravel())),
                       shape=(m.n_nodes, m.n_nodes))
    _, lab = connected_components(g, directed=False)
    tum = np.unique(m.tets[m.material_ids == 1])
    assert not set(lab[tum].tolist()) & set(lab[sim.fem.fixed_nodes].tolist())


def test_bite_spares_the_tumour(sim):
    m = sim.mesh
    n_tum = int((m.material_ids == 1).sum())
    c = sim.positions()[m.tets[m.material_ids == 1]].mean(axis=(0, 1))
    r, rad = spare_tumour_bite(sim, c, 0.01)  # aimed at the tumour's middle
    assert not r.changed and rad < 0.01
    assert int((sim.mesh.material_ids == 1).sum()) == n_tum


def test_the_specimen_is_lifted_out_once_free():
    """After the attachment cut is removed, the specimen (every part holding tumour and no fixed
    node) is lifted out: no tumour is left, the base stays, nothing attached to it goes."""
    with load_scene("brain_resection.yaml", device="cpu") as s:
        assert not specimen_tets(s).any()  # attached: nothing to lift out yet
        assert s.remove_tets(attachment_cut(s)).changed
        assert tumour_freed(s)
        spec = specimen_tets(s)
        m = s.mesh
        assert spec[m.material_ids == 1].all()
        assert not np.isin(m.tets[spec], s.fem.fixed_nodes).any()
        n_fixed = len(s.fem.fixed_nodes)
        r = s.remove_tets(spec)
        assert r.changed and r.tets_changed == spec.sum()
        assert not (s.mesh.material_ids == 1).any() and len(s.fem.fixed_nodes) == n_fixed


def _pedal_down_runs(acts):
    """The scalpel's paths while the pedal is down, each with the act before it."""
    runs, cur = [], None
    for k, a in enumerate(acts):
        if a["cutting"]:
            if cur is None:
                cur = {"before": acts[k - 1], "path": []}
                runs.append(cur)
            cur["path"].append(np.asarray(a["scalpel"], float))
        else:
            cur = None
    return runs


def test_the_long_session_adds_an_outer_cut_and_radial_wedges(sim):
    """The long session's script: an outer spiral ``margin`` outside the inner one, then
    ``radial`` radial cuts between the two, each one stroke that enters from above along the
    outer cut and passes back and forth between the cuts at levels at most 10 mm apart (the
    blade is 12 mm, so the passes overlap), its vertical moves only along a cut. Each stroke
    starts with the pedal up and the blade out of the tissue, so no blade is swept from its
    home into the brain."""
    from soft_tissue_sim.scenarios.brain import plan, tumour_geometry

    m = sim.mesh
    c, r, _, _ = tumour_geometry(m)
    R, margin, radial = r + 0.006, 0.010, 8
    short = _pedal_down_runs(plan(m))
    assert len(short) == 1  # the standard session: one spiral
    runs = _pedal_down_runs(plan(m, margin=margin, radial=radial))
    top = m.points[:, 2].max()
    for run in runs:
        assert not run["before"]["cutting"] and run["before"]["scalpel"][2] > top  # blade out, pedal up
    outer, inner, *wedges = runs
    rad = lambda p: np.linalg.norm(np.asarray(p)[..., :2] - c[:2], axis=-1)  # noqa: E731
    assert np.allclose(rad(np.array(outer["path"])), R + margin)
    assert np.allclose(np.array(inner["path"]), np.array(short[0]["path"]))
    assert len(wedges) == radial
    angles = set()
    for w in wedges:
        p = np.array(w["path"])
        d = rad(p)
        assert np.all((d > R - 1e-9) & (d < R + margin + 1e-9))
        assert p[0, 2] > top and np.isclose(d[0], R + margin)  # the blade (12 mm up from p) starts out, over the outer cut
        step = np.diff(p, axis=0)
        vertical = np.abs(step[:, 2]) > 1e-12
        assert np.all(np.linalg.norm(step[vertical, :2], axis=1) < 1e-12)  # a move is vertical or level
        ends = d[1:][vertical]
        assert np.all(np.isclose(ends, R) | np.isclose(ends, R + margin))  # vertical only along a cut
        zs = np.unique(np.round(p[1:][~vertical, 2], 9))
        assert np.max(np.diff(zs)) <= 0.010 + 1e-9
        assert np.isclose(zs.min(), inner["path"][-1][2])  # down to the inner spiral's floor
        angles.add(round(float(np.arctan2(p[-1, 1] - c[1], p[-1, 0] - c[0])), 6))
    assert len(angles) == radial


@pytest.mark.parametrize("args", [["--radial", "4"], ["--margin", "0.01"], ["--margin", "-0.01", "--radial", "2"]])
def test_the_long_session_needs_both_a_margin_and_radial_cuts(args, tmp_path):
    """A margin without radial cuts (or the reverse, or a negative margin) is refused before
    anything is built, with argparse's usage error."""
    from soft_tissue_sim.bench import brain

    with pytest.raises(SystemExit) as e:
        brain.main(args + ["--out", str(tmp_path)])
    assert e.value.code == 2
    assert not any(tmp_path.iterdir())


def test_a_negative_lag_is_refused(tmp_path):
    """``--lag`` (the paper's factorization delay, reproducibly) is a number of steps >= 0."""
    from soft_tissue_sim.bench import brain

    with pytest.raises(SystemExit) as e:
        brain.main(["--lag", "-1", "--out", str(tmp_path)])
    assert e.value.code == 2
    assert not any(tmp_path.iterdir())


def test_the_aspiration_keeps_the_floor_under_the_specimen(sim):
    """The planned bites part the tissue under the tumour but leave the floor of the cut: at
    rest, every fixed node under the disc they cover keeps a tet (the base is not opened, so
    the specimen has something to rest on as it comes free; the earlier plan, a layer lower,
    left 10 of these 19 nodes bare), and the bites take tissue between the floor and the
    tumour over the whole disc inside the cut."""
    from soft_tissue_sim.scenarios.brain import plan, tumour_geometry

    m = sim.mesh
    cen = m.centroids()
    c, r, zlo, _ = tumour_geometry(m)
    fixed = np.zeros(m.n_nodes, bool)
    fixed[sim.fem.fixed_nodes] = True
    under = fixed & (np.linalg.norm(m.points[:, :2] - c[:2], axis=1) < r + 0.006)
    bites = [a["remove"] for a in plan(m) if "remove" in a]
    taken = np.zeros(m.n_tets, bool)
    for centre, radius in bites:
        taken |= np.linalg.norm(cen - centre, axis=1) < radius
    kept = np.zeros(m.n_nodes, bool)
    kept[m.tets[~taken]] = True
    assert under.sum() >= 10 and kept[under].all()
    assert (taken & (m.material_ids == 0)).sum() > 100  # the tissue under the tumour goes
    zs = np.array([b[0][2] for b in bites])
    assert zs.max() < zlo  # under the tumour
    xy = np.array([b[0][:2] for b in bites]) - c[:2]
    assert np.linalg.norm(xy, axis=1).max() > r  # out to the cut (6 mm outside the tumour)
