"""The brain bench's closed-loop surgeon: the attachment cut and the tumour-sparing bite
(topology and geometry only, on the rest state: no time stepping)."""

import numpy as np
import pytest

from soft_tissue_sim.bench.brain import attachment_cut, spare_tumour_bite, specimen_tets, tumour_freed
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
