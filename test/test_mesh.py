"""Tet meshes: validation errors, meshio round trips, generators, surface orientation, CLI."""

import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest

from soft_tissue_sim.mesh import (
    MeshError,
    TetMesh,
    beam_mesh,
    brain_mesh,
    cli,
    edge_table,
    edge_table_after_change,
    grid_mesh,
    insert_rows,
    interior_faces,
    node_ring,
    interior_faces_after_removal,
    interior_faces_after_split,
    load_mesh,
    save_mesh,
    tet_quality,
    unique_rows,
    validate_mesh,
)

REPO = Path(__file__).resolve().parents[1]
REGULAR = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], dtype=float)  # positive order


@pytest.fixture(scope="module")
def brain():
    return brain_mesh()


def small():
    return beam_mesh(3, n_cross=2, spacing=0.01)  # 12 nodes, 12 tets


# ---------------------------------------------------------------- quality


@pytest.mark.parametrize("high", [7, 50_000, 2**40])  # packed keys (3 and 4 columns), and the fallback
def test_unique_rows_matches_numpy(high):
    rng = np.random.default_rng(3)
    for w in (2, 3, 4):
        rows = rng.integers(0, high, size=(400, w))
        rows = np.concatenate([rows, rows[::7]])  # repeats
        got = unique_rows(rows, return_index=True, return_inverse=True, return_counts=True)
        want = np.unique(rows, axis=0, return_index=True, return_inverse=True, return_counts=True)
        for g, e in zip(got, want):
            np.testing.assert_array_equal(g, e)
        np.testing.assert_array_equal(unique_rows(rows), np.unique(rows, axis=0))
    assert unique_rows(np.zeros((0, 3), np.int64)).shape == (0, 3)


def test_tet_quality_regular_flat_inverted():
    t = np.array([[0, 1, 2, 3]])
    assert tet_quality(REGULAR, t)[0] == pytest.approx(1.0, abs=1e-12)
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.linalg.det(q))  # proper rotation
    assert tet_quality(0.003 * REGULAR @ q.T + 5.0, t)[0] == pytest.approx(1.0, abs=1e-12)
    flat = REGULAR.copy()
    flat[3] = (flat[0] + flat[1] + flat[2]) / 3 + 1e-9
    assert abs(tet_quality(flat, t)[0]) < 1e-8
    assert tet_quality(REGULAR, np.array([[0, 2, 1, 3]]))[0] == pytest.approx(-1.0, abs=1e-12)
    # a Kuhn tet of a cube: V = 1/6, l_rms^2 = 10/6
    kuhn = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]], float)
    assert tet_quality(kuhn, t)[0] == pytest.approx(np.sqrt(2) / (10 / 6) ** 1.5)


# ---------------------------------------------------------------- validation


def _bad_cases():
    m = small()
    P, T = m.points, m.tets.astype(np.int64)
    cases = {}
    cases["no_tets"] = (P, np.zeros((0, 4), int), "no tetrahedra", None)
    cases["points_shape"] = (P[:, :2], T, "points must have shape (n, 3)", None)
    cases["tets_shape"] = (P, T[:, :3], "tets must have shape (m, 4)", None)
    p = P.copy()
    p[7, 1] = np.nan
    p[9, 2] = np.inf
    cases["nan"] = (p, T, "non-finite", "[7, 9]")
    t = T.copy()
    t[5, 2] = len(P)
    cases["out_of_range"] = (P, t, "out of range", "[5]")
    t = T.copy()
    t[4, 3] = t[4, 0]
    cases["repeated"] = (P, t, "repeated node", "[4]")
    t = T.copy()
    t[6, [1, 2]] = t[6, [2, 1]]
    cases["inverted"] = (P, t, "inverted", "[6]")
    p = P.copy()
    t = T.copy()
    p = np.vstack([p, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 0.0]]])  # coplanar
    t = np.vstack([t, [[12, 13, 14, 15]]])
    cases["degenerate"] = (p, t, "degenerate", "[12]")
    t = np.vstack([T, T[3][[2, 0, 3, 1]]])
    cases["duplicated"] = (P, t, "duplicated", "[12]")
    return cases


@pytest.mark.parametrize("name", list(_bad_cases()))
def test_validate_rejects_bad_input(name):
    P, T, problem, index = _bad_cases()[name]
    P0, T0 = np.array(P, copy=True), np.array(T, copy=True)
    with pytest.raises(MeshError) as e:
        validate_mesh(P, T)
    msg = str(e.value)
    assert problem in msg
    if index is not None:
        assert index in msg
    assert np.array_equal(P, P0, equal_nan=True) and np.array_equal(T, T0)  # inputs untouched


def test_validate_lists_first_ten_then_count():
    m = beam_mesh(4, n_cross=3)
    t = m.tets.copy()
    t[:, [0, 1]] = t[:, [1, 0]]  # invert all
    with pytest.raises(MeshError, match=r"inverted .*\[0, 1, 2, 3, 4, 5, 6, 7, 8, 9\] and 62 more \(72 in all\)"):
        validate_mesh(m.points, t)


def test_validate_material_ids_checked():
    m = small()
    with pytest.raises(MeshError, match="material_ids must have shape"):
        validate_mesh(m.points, m.tets, np.zeros(m.n_tets + 1))
    with pytest.raises(MeshError, match="material ids must be integers"):
        validate_mesh(m.points, m.tets, np.full(m.n_tets, 0.5))
    out = validate_mesh(m.points, m.tets, np.arange(m.n_tets, dtype=np.int64))
    assert out.material_ids.dtype == np.int32 and np.array_equal(out.material_ids, np.arange(m.n_tets))
    assert np.array_equal(validate_mesh(m.points, m.tets).material_ids, np.zeros(m.n_tets))


def test_unreferenced_nodes_dropped_and_indices_remapped():
    m = small()
    rng = np.random.default_rng(1)
    n = m.n_nodes
    # new layout: 3 unused nodes spread among the real ones
    new_of_old = np.setdiff1d(np.arange(n + 3), [0, 5, n + 2])
    P = rng.standard_normal((n + 3, 3))
    P[new_of_old] = m.points
    T = new_of_old[m.tets]
    mat = np.arange(m.n_tets) % 3
    with pytest.warns(UserWarning, match=r"dropping 3 node\(s\).*\[0, 5, 14\]"):
        out = validate_mesh(P, T, mat)
    assert out.n_nodes == n
    assert np.array_equal(out.points, m.points)
    assert np.array_equal(out.tets, m.tets)
    assert np.array_equal(out.material_ids, mat)
    assert np.allclose(out.signed_volumes(), m.signed_volumes())


def test_clean_mesh_gives_no_warning():
    m = small()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = validate_mesh(m.points, m.tets)
    assert out.tets.dtype == np.int32 and out.points.dtype == np.float64


# ---------------------------------------------------------------- I/O


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_round_trip(tmp_path, brain, suffix):
    path = tmp_path / f"brain{suffix}"
    save_mesh(brain, path)
    back = load_mesh(path)
    assert np.allclose(back.points, brain.points, rtol=0, atol=1e-12)
    assert np.array_equal(back.tets, brain.tets)
    assert np.array_equal(back.material_ids, brain.material_ids)
    assert set(np.unique(back.material_ids)) == {0, 1}
    if suffix == ".msh":
        with open(path, "rb") as fh:
            head = fh.read(40)
        assert b"$MeshFormat\n2.2" in head


def test_material_key_fallback_and_explicit(tmp_path):
    m = small()
    ids = (np.arange(m.n_tets) % 4).astype(np.int32)
    other = (10 + np.arange(m.n_tets)).astype(np.int32)
    path = tmp_path / "keys.vtu"
    meshio.write(path, meshio.Mesh(m.points, [("tetra", m.tets)], cell_data={"MaterialIds": [ids], "other": [other]}))
    assert np.array_equal(load_mesh(path).material_ids, ids)
    assert np.array_equal(load_mesh(path, material_key="other").material_ids, other)
    with pytest.raises(MeshError, match="no cell data 'missing'"):
        load_mesh(path, material_key="missing")


def test_tetra_blocks_concatenated_and_surface_cells_ignored(tmp_path):
    m = small()
    ids = np.arange(m.n_tets, dtype=np.int32)
    tri = m.boundary_faces()
    cells = [("tetra", m.tets[:5]), ("triangle", tri), ("tetra", m.tets[5:])]
    data = {"gmsh:physical": [ids[:5], np.full(len(tri), 99), ids[5:]]}
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(m.points, cells, cell_data=data))
    back = load_mesh(path)
    assert np.array_equal(back.tets, m.tets)
    assert np.array_equal(back.material_ids, ids)


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.vtu"):
        load_mesh(tmp_path / "nowhere.vtu")
    m = small()
    tri = tmp_path / "surface.vtu"
    meshio.write(tri, meshio.Mesh(m.points, [("triangle", m.boundary_faces())]))
    with pytest.raises(MeshError, match=r"no tetrahedra.*triangle \(\d+\)"):
        load_mesh(tri)
    quad = tmp_path / "quadratic.vtu"
    meshio.write(quad, meshio.Mesh(np.vstack([m.points] * 3), [("tetra10", np.arange(10)[None, :])]))
    with pytest.raises(MeshError, match="quadratic"):
        load_mesh(quad)
    hexa = tmp_path / "hex.vtu"
    meshio.write(hexa, meshio.Mesh(m.points, [("tetra", m.tets), ("hexahedron", np.arange(8)[None, :])]))
    with pytest.raises(MeshError, match="hexahedron"):
        load_mesh(hexa)
    junk = tmp_path / "junk.vtu"
    junk.write_text("not a mesh")
    with pytest.raises(MeshError, match="cannot read mesh file"):
        load_mesh(junk)
    bad = tmp_path / "inverted.vtu"
    t = m.tets.copy()
    t[2, [0, 1]] = t[2, [1, 0]]
    meshio.write(bad, meshio.Mesh(m.points, [("tetra", t)]))
    with pytest.raises(MeshError, match=r"inverted.*\[2\]"):
        load_mesh(bad)


# ---------------------------------------------------------------- generators


@pytest.mark.parametrize("n_long,nodes", [(48, 1200), (64, 1600), (80, 2000)])
def test_paper_beams(n_long, nodes):
    m = beam_mesh(n_long)
    assert m.n_nodes == nodes and m.n_tets == 6 * 16 * (n_long - 1)
    v = m.signed_volumes()
    assert v.min() > 0
    L = (n_long - 1) * 0.01
    assert v.sum() == pytest.approx(L * 0.04 * 0.04, rel=1e-12)
    assert np.allclose(m.points.min(0), [0, -0.02, -0.02]) and np.allclose(m.points.max(0), [L, 0.02, 0.02])
    # conforming split: the only faces used once are the 2 triangles of each surface quad
    quads = 2 * 4 * 4 + 4 * (n_long - 1) * 4
    assert len(m.boundary_faces()) == 2 * quads


def test_beam_length_width_and_errors():
    m = beam_mesh(11, n_cross=3, length=0.5, width=0.1)
    assert np.allclose(m.points.max(0) - m.points.min(0), [0.5, 0.1, 0.1])
    assert m.signed_volumes().sum() == pytest.approx(0.5 * 0.1 * 0.1)
    with pytest.raises(MeshError, match="n_long"):
        beam_mesh(1)
    with pytest.raises(MeshError, match="spacing"):
        beam_mesh(5, spacing=0.0)
    with pytest.raises(MeshError, match="width"):
        beam_mesh(5, width=float("nan"))


def test_brain(brain):
    assert brain.n_nodes == 1734 and brain.n_tets == 7680
    assert brain.signed_volumes().min() > 0
    assert tet_quality(brain.points, brain.tets).min() > 0.05
    ids = brain.material_ids
    assert set(np.unique(ids)) == {0, 1}
    c = brain.centroids()
    d = np.linalg.norm(c - [0.01, 0.0, 0.03], axis=1)
    assert np.all(d[ids == 1] < 0.014) and np.all(d[ids == 0] >= 0.014)
    # the tumour tets fill roughly the sphere's volume
    sphere = 4 / 3 * np.pi * 0.014**3
    assert brain.signed_volumes()[ids == 1].sum() == pytest.approx(sphere, rel=0.15)
    # flat base at z = 0 made of boundary faces with downward normals
    assert brain.points[:, 2].min() == 0.0
    f = brain.boundary_faces()
    base = f[np.all(brain.points[f, 2] == 0.0, axis=1)]
    x = brain.points[base]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    assert len(base) == 2 * 16 * 16 and np.all(n[:, 2] < 0)
    ext = brain.points.max(0) - brain.points.min(0)
    assert np.allclose(ext, [0.14, 0.11, 0.05])
    assert brain_mesh().points.tobytes() == brain.points.tobytes()  # deterministic


# ---------------------------------------------------------------- topology


@pytest.mark.parametrize("which", ["beam", "brain"])
def test_boundary_closed_and_outward(which, brain):
    m = beam_mesh(12, n_cross=4, spacing=0.013) if which == "beam" else brain
    f = m.boundary_faces()
    assert f.dtype == np.int32
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    # closed and consistently oriented: every directed edge once, its reverse exactly once
    fwd = {tuple(e) for e in directed}
    assert len(fwd) == len(directed)
    assert all((b, a) in fwd for a, b in fwd)
    und, cnt = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(cnt == 2)
    # outward: divergence theorem, volume = sum (centroid . n) area / 3
    x = m.points[f]
    cross = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    vol_surface = np.einsum("ij,ij->", x.mean(axis=1), cross) / 6.0
    assert vol_surface == pytest.approx(m.signed_volumes().sum(), rel=1e-10)


def test_edges_and_euler_characteristic(brain):
    for m in (beam_mesh(7, n_cross=3), brain):
        e = m.edges()
        assert np.all(e[:, 0] < e[:, 1]) and len(np.unique(e, axis=0)) == len(e)
        every = m.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
        assert np.array_equal(e, np.unique(np.sort(every, axis=1), axis=0))  # sorted rows, each edge once
        faces = np.unique(np.sort(m.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1), axis=0)
        assert m.n_nodes - len(e) + len(faces) - m.n_tets == 1  # a ball
    one = TetMesh(REGULAR, np.array([[0, 1, 2, 3]]))
    assert one.edges().tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]


@pytest.mark.parametrize("scale", [1, 2**21])  # packed face keys, and the lexsort fallback
def test_interior_faces_pair_the_tets_that_share_a_face(brain, scale):
    from soft_tissue_sim.mesh import _FACES

    T = brain.tets.astype(np.int64) * scale  # node ids spread out, their order kept
    pairs, fnodes, tet_face = interior_faces(T)
    owners = {}
    for t, tet in enumerate(T.tolist()):
        for k, f in enumerate(_FACES.tolist()):
            owners.setdefault(tuple(sorted(tet[i] for i in f)), []).append((t, k))
    assert max(len(v) for v in owners.values()) == 2
    inner = sorted((key, v) for key, v in owners.items() if len(v) == 2)
    assert fnodes.tolist() == [list(key) for key, _ in inner]  # sorted by node triples
    assert pairs.tolist() == [[v[0][0], v[1][0]] for _, v in inner]
    expect = np.full((len(T), 4), -1)
    for f, (_, v) in enumerate(inner):
        for t, k in v:
            expect[t, k] = f
    np.testing.assert_array_equal(tet_face, expect)
    assert pairs.dtype == fnodes.dtype == tet_face.dtype == np.int64


def test_interior_faces_are_cached_until_the_tets_change():
    m = beam_mesh(4, n_cross=3)
    f = m.interior_faces()
    assert m.interior_faces() is f
    with pytest.raises(ValueError):
        f[0][0, 0] = 3  # read-only: shared by every caller
    m.tets = m.tets[::-1].copy()  # replaced
    g = m.interior_faces()
    assert g is not f and all(np.array_equal(a, b) for a, b in zip(g, interior_faces(m.tets)))
    m.tets[:2] = m.tets[1::-1].copy()  # changed in place
    h = m.interior_faces()
    assert h is not g and all(np.array_equal(a, b) for a, b in zip(h, interior_faces(m.tets)))
    assert not np.array_equal(h[2], g[2])


def _random_split(rng, T, n, nodes=12):
    """Tets T with random nodes copied: each picked node's copy takes its place in a random
    subset of its tets (any subset: faces may part anywhere). (new tets, copy_of)."""
    T = T.copy()
    copy_of = list(range(n))
    for v in rng.choice(n, nodes, replace=False):
        at = np.flatnonzero(np.any(T == v, axis=1))
        at = at[rng.random(len(at)) < 0.5]
        if len(at):
            T[at] = np.where(T[at] == v, len(copy_of), T[at])
            copy_of.append(int(v))
    return T, np.array(copy_of)


@pytest.mark.parametrize("seed", range(4))
def test_interior_faces_derived_after_a_split_or_a_removal_equal_the_recomputed_ones(brain, seed):
    """The tables derived from the old mesh's after a node split and after an element removal
    (with node compaction) are exactly :func:`interior_faces` of the new tets; a relabelling
    that is no split is refused (None)."""
    rng = np.random.default_rng(seed)
    T0 = brain.tets.astype(np.int64)
    faces = interior_faces(T0)
    T1, copy_of = _random_split(rng, T0, brain.n_nodes)
    got = interior_faces_after_split(faces, T0, T1, copy_of)
    expect = interior_faces(T1)
    assert len(expect[0]) < len(faces[0])  # faces did part
    for a, b in zip(got, expect):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    wrong = copy_of.copy()
    wrong[-1] = (wrong[-1] + 1) % brain.n_nodes
    assert interior_faces_after_split(faces, T0, T1, wrong) is None
    faces1 = expect
    kept = rng.random(len(T1)) < 0.9
    used = np.zeros(len(copy_of), bool)
    used[T1[kept].ravel()] = True
    keep = np.flatnonzero(used)
    remap = np.cumsum(used) - 1
    got = interior_faces_after_removal(faces1, kept, keep, len(copy_of))
    for a, b in zip(got, interior_faces(remap[T1[kept]])):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype


def test_an_installed_interior_face_table_is_the_cache_until_the_tets_change():
    m = beam_mesh(4, n_cross=3)
    assert m.cached_interior_faces() is None
    table = interior_faces(m.tets)
    m.set_interior_faces(table)
    f = m.cached_interior_faces()
    assert f is m.interior_faces() and all(np.array_equal(a, b) for a, b in zip(f, table))
    m.tets[:2] = m.tets[1::-1].copy()
    assert m.cached_interior_faces() is None


def test_tetmesh_checks_shapes():
    with pytest.raises(MeshError, match="points must have shape"):
        TetMesh(np.zeros((6, 2)), np.array([[0, 1, 2, 3]]))
    with pytest.raises(MeshError, match="material_ids must have shape"):
        TetMesh(REGULAR, np.array([[0, 1, 2, 3]]), np.zeros(2))


def test_copy_is_independent():
    m = small()
    c = m.copy()
    c.points[0] += 1.0
    c.tets[0, 0] = 99
    c.material_ids[0] = 5
    assert m.points[0, 0] == 0.0 and m.tets[0, 0] != 99 and m.material_ids[0] == 0


# ---------------------------------------------------------------- CLI and committed files


def test_cli_beam_brain_info(tmp_path, capsys):
    out = tmp_path / "sub" / "b.vtu"
    assert cli(["beam", "--long", "6", "--cross", "3", "--spacing", "0.02", "--out", str(out)]) == 0
    ref = beam_mesh(6, n_cross=3, spacing=0.02)
    back = load_mesh(out)
    assert np.array_equal(back.tets, ref.tets) and np.allclose(back.points, ref.points)
    capsys.readouterr()
    assert cli(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nodes         54" in text and "tets          120" in text and "0: 120" in text
    with pytest.raises(SystemExit) as e:
        cli(["info", str(tmp_path / "missing.vtu")])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        cli(["beam", "--long", "1", "--out", str(out)])
    assert e.value.code == 2


@pytest.mark.parametrize("name,make", [
    ("beam_1200.vtu", lambda: beam_mesh(48)),
    ("beam_1600.vtu", lambda: beam_mesh(64)),
    ("beam_2000.vtu", lambda: beam_mesh(80)),
    ("brain.vtu", brain_mesh),
])
def test_committed_meshes_match_generators(name, make):
    path = REPO / "meshes" / name
    assert path.stat().st_size < 1_000_000
    got, ref = load_mesh(path), make()
    assert np.array_equal(got.points, ref.points)
    assert np.array_equal(got.tets, ref.tets)
    assert np.array_equal(got.material_ids, ref.material_ids)


def _edge_table_from_scratch(T):
    every = np.sort(np.asarray(T, np.int64)[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1)
    return np.unique(every, axis=0, return_counts=True)


def test_edge_table_counts_the_tets_of_each_edge(brain):
    for T in (brain.tets, beam_mesh(5, n_cross=3).tets, brain.tets.astype(np.int64) * 2**31):  # last: no packed keys
        e, c = edge_table(T)
        ref_e, ref_c = _edge_table_from_scratch(T)
        np.testing.assert_array_equal(e, ref_e)
        np.testing.assert_array_equal(c, ref_c)
        assert e.dtype == c.dtype == np.int64


@pytest.mark.parametrize("seed", range(4))
def test_edge_table_derived_after_a_split_a_removal_or_new_tets_equals_the_recomputed_one(brain, seed):
    """The edge table (edges and their tet counts) derived from the old mesh's after a node
    split, a removal with node compaction and a change that puts in tets on new nodes, is
    exactly :func:`edge_table` of the new tets; a change the table does not fit is refused."""
    rng = np.random.default_rng(seed)
    T0 = brain.tets.astype(np.int64)
    table = edge_table(T0)
    T1, copy_of = _random_split(rng, T0, brain.n_nodes)  # a split: the changed tets out, their new selves in
    changed = np.flatnonzero(np.any(T1 != T0, axis=1))
    got = edge_table_after_change(table, T0[changed], T1[changed], np.arange(brain.n_nodes), len(copy_of))
    expect = edge_table(T1)
    assert len(expect[0]) > len(table[0])  # edges were added
    for a, b in zip(got, expect):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    kept = rng.random(len(T1)) < 0.9  # a removal with node compaction
    used = np.zeros(len(copy_of), bool)
    used[T1[kept].ravel()] = True
    remap = np.where(used, np.cumsum(used) - 1, -1)
    got = edge_table_after_change(expect, T1[~kept], np.zeros((0, 4), np.int64), remap, int(used.sum()))
    for a, b in zip(got, edge_table(remap[T1[kept]])):
        np.testing.assert_array_equal(a, b)
    n = len(copy_of)  # a subdivision-like change: tets out, tets on new nodes and old ones in
    out = rng.choice(len(T1), 20, replace=False)
    new = np.concatenate([T1[out][:, [0, 1, 2]], n + np.arange(20)[:, None]], axis=1)
    T2 = np.concatenate([np.delete(T1, out, axis=0), new])
    got = edge_table_after_change(expect, T1[out], new, np.arange(n), n + 20)
    for a, b in zip(got, edge_table(T2)):
        np.testing.assert_array_equal(a, b)
    assert edge_table_after_change(expect, T1[out] + 1, new, np.arange(n), n + 20) is None  # not its tets
    assert edge_table_after_change(expect, T1[out], new, np.arange(n)[::-1].copy(), n + 20) is None  # reorders
    assert edge_table_after_change(expect, T1[:0], new, np.where(np.arange(n) == 5, -1, np.arange(n)), n + 20) is None


@pytest.mark.parametrize("shape, dtype", [((), np.int64), ((2,), np.int64), ((3,), np.int32), ((2, 2), np.float64)])
def test_insert_rows_is_numpys_insert(shape, dtype):
    """insert_rows gives np.insert's rows along the first axis for non-decreasing positions:
    at the start, the end, several at one place, none, into an empty array."""
    rng = np.random.default_rng(1)
    for n in (0, 1, 7, 300):
        for k in (0, 1, 3, 40):
            a = rng.integers(-99, 99, (n, *shape)).astype(dtype)
            rows = rng.integers(-99, 99, (k, *shape)).astype(dtype)
            pos = np.sort(rng.integers(0, n + 1, k))
            if k > 1:
                pos[0], pos[-1] = 0, n
            got = insert_rows(a, pos, rows)
            expect = np.insert(a, pos, rows, axis=0)
            np.testing.assert_array_equal(got, expect)
            assert got.dtype == expect.dtype and got.shape == expect.shape


def test_node_ring_is_the_sorted_adjacency_of_the_edges(brain):
    import scipy.sparse as sps

    for m in (brain, beam_mesh(5, n_cross=3), TetMesh(np.zeros((70_000, 3)), np.array([[0, 1, 69_999, 3]]))):
        e = m.edges()
        n = m.n_nodes
        adj = sps.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        adj = (adj + adj.T).tocsr()
        adj.sort_indices()
        offsets, ring = node_ring(m.edge_table()[0], n)
        np.testing.assert_array_equal(offsets, adj.indptr)
        np.testing.assert_array_equal(ring, adj.indices)
        assert offsets.dtype == ring.dtype == np.int32


def test_node_components_equal_scipys_numbering_of_the_tet_graph(brain):
    """The parts from the node ring are labelled as scipy labels the graph of the tets (the
    order of their lowest node); a node in no tet is a part of its own."""
    import scipy.sparse as sps
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(1)
    for k in range(3):
        T = brain.tets[rng.random(brain.n_tets) < 0.05 + 0.05 * k]  # many parts, some lone nodes
        perm = rng.permutation(brain.n_nodes)  # parts' lowest nodes in another order
        m = TetMesh(brain.points, perm[T])
        rows, cols = np.repeat(m.tets[:, 0], 3), m.tets[:, 1:].ravel()
        g = sps.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m.n_nodes, m.n_nodes))
        ref = connected_components(g, directed=False)[1]
        assert ref.max() > 3
        lab = m.node_components()
        np.testing.assert_array_equal(lab, ref)
        assert lab.dtype == ref.dtype


def test_connectivity_tables_are_cached_until_the_tets_or_node_count_change():
    m = beam_mesh(4, n_cross=3)
    t, r, c = m.edge_table(), m.node_ring(), m.node_components()
    assert m.edge_table() is t and m.node_ring() is r and m.node_components() is c
    with pytest.raises(ValueError):
        c[0] = 3  # read-only: shared by every caller
    m.tets[:1] = m.tets[1:2].copy()  # changed in place
    assert m.edge_table() is not t
    np.testing.assert_array_equal(m.edge_table()[0], _edge_table_from_scratch(m.tets)[0])
    c = m.node_components()
    m.points = np.concatenate([m.points, np.zeros((1, 3))])  # a node in no tet
    assert m.node_components() is not c and m.node_components().max() == c.max() + 1
    assert m.cached_edge_table() is not None  # installed tables come back until the tets change
    table = edge_table(m.tets)
    m.set_edge_table(table)
    assert all(np.array_equal(a, b) for a, b in zip(m.cached_edge_table(), table))
    m.tets = m.tets[::-1].copy()
    assert m.cached_edge_table() is None


def test_boundary_faces_are_the_tets_faces_without_a_neighbour_in_tet_order(brain):
    from soft_tissue_sim.mesh import _FACES

    for m in (brain, TetMesh(brain.points, brain.tets[np.random.default_rng(0).random(brain.n_tets) < 0.5])):
        f = m.boundary_faces()
        expect = m.tets[:, _FACES].reshape(-1, 3)[interior_faces(m.tets)[2].ravel() < 0]
        np.testing.assert_array_equal(f, expect)
        assert f.dtype == np.int32 and f.flags.c_contiguous


def test_centroids_are_the_mean_of_the_gathered_nodes_bit_for_bit(brain):
    from soft_tissue_sim.mesh import centroids

    rng = np.random.default_rng(3)
    for scale in (1.0, 1e-3, 1e7):
        pts = brain.points + scale * rng.standard_normal(brain.points.shape)
        got = centroids(pts, brain.tets)
        assert np.array_equal(got.view(np.uint64), pts[brain.tets].mean(axis=1).view(np.uint64))


@pytest.mark.parametrize("traversal", ["scipy's traversal", "public function"])
def test_ring_components_equal_scipys_connected_components_on_random_graphs(monkeypatch, traversal):
    """The parts of a node ring, by scipy's undirected traversal run on the ring directly (or
    the public function where that is not available), are scipy's labels of the same graph."""
    import scipy.sparse as sps
    from scipy.sparse.csgraph import connected_components

    import soft_tissue_sim.mesh as mesh_mod

    if traversal == "public function":
        monkeypatch.setattr(mesh_mod, "_undirected_traversal", None)
    rng = np.random.default_rng(7)
    for n, m in ((1, 0), (30, 4), (200, 40), (500, 300)):
        T = np.stack([rng.choice(n, 4, replace=False) for _ in range(m)]) if n >= 4 and m else np.zeros((0, 4), int)
        mesh = TetMesh(rng.random((n, 3)), T)
        offsets, ring = mesh.node_ring()
        ref = connected_components(sps.csr_matrix((np.ones(len(ring)), ring, offsets), shape=(n, n)),
                                   directed=False)[1]
        lab = mesh_mod.ring_components(offsets, ring, n)
        np.testing.assert_array_equal(lab, ref)
        assert lab.dtype == np.int32
        np.testing.assert_array_equal(mesh.node_components(), ref)


def test_boundary_faces_equal_the_gather_by_tet_and_local_face_on_random_meshes():
    """The boundary faces gathered from the flat tets are the rows ``tets[t, _FACES[j]]`` of the
    faces without a neighbour, in the order of 4 t + j (int32, C-ordered)."""
    from soft_tissue_sim.mesh import _FACES

    rng = np.random.default_rng(3)
    base = grid_mesh(np.linspace(0, 1, 5), np.linspace(0, 1, 4), np.linspace(0, 1, 4))
    for keep in (1.0, 0.7, 0.2):
        T = base.tets[rng.random(base.n_tets) < keep]
        m = TetMesh(base.points, T)
        tet_face = m.interior_faces()[2]
        k = np.flatnonzero(tet_face.ravel() < 0)
        ref = np.array([m.tets[i // 4, _FACES[i % 4]] for i in k], np.int32).reshape(-1, 3)
        bf = m.boundary_faces()
        np.testing.assert_array_equal(bf, ref)
        assert bf.dtype == np.int32 and bf.flags.c_contiguous
