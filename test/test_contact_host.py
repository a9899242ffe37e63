"""The host side of a contact step against the straightforward NumPy forms it replaces: the
cross products, the reading of a detection's slots, the contacts' friction coefficients, the
contact names, the records' selection, the staging buffer's runs of fields. Results must be
the same bits, not merely close."""

import dataclasses

import numpy as np
import pytest

from soft_tissue_sim.buffers import field_runs
from soft_tissue_sim.contact.detection import Section, SlotMap, collect
from soft_tissue_sim.contact.records import Contacts
from soft_tissue_sim.contact.solver import ContactSolver
from soft_tissue_sim.contact.warm import contact_names
from soft_tissue_sim.mesh import cross


def same_bits(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("shapes", [((7, 3), (7, 3)), ((3,), (5, 3)), ((5, 3), (3,)), ((2, 4, 3), (2, 4, 3)),
                                    ((0, 3), (0, 3))])
def test_cross_is_numpys_cross_to_the_bit(shapes):
    rng = np.random.default_rng(1)
    u, v = (rng.standard_normal(s) for s in shapes)
    assert same_bits(cross(u, v), np.cross(u, v))
    out = np.full(np.broadcast_shapes(*shapes), np.nan)
    assert cross(u, v, out=out) is out
    assert same_bits(out, np.cross(u, v))


def test_cross_writes_into_a_strided_view():
    rng = np.random.default_rng(2)
    u, v = rng.standard_normal((6, 3)), rng.standard_normal((6, 3))
    terms = np.zeros((6, 6))
    cross(u, v, out=terms[:, 3:])
    assert same_bits(terms[:, 3:], np.cross(u, v)) and not terms[:, :3].any()


def test_field_runs_group_adjacent_fields_in_layout_order():
    order = ["a", "b", "c", "d", "e", "f"]
    rng = np.random.default_rng(3)
    for _ in range(50):
        names = set(rng.choice(order, size=rng.integers(1, 7), replace=False))
        runs = field_runs(order, names)
        covered = [order[i] for a, b in runs for i in range(order.index(a), order.index(b) + 1)]
        assert covered == [k for k in order if k in names]  # every field once, in layout order
        for (_, last), (first, _) in zip(runs, runs[1:]):  # runs are maximal
            assert order.index(first) > order.index(last) + 1
    assert field_runs(order, ("f", "a", "b")) == [("a", "b"), ("f", "f")]


def _collect_reference(slots, faces, host):
    """The contacts of a detection's slots as first written: kind by kind, the triangle rows filled in."""
    active, gap, normal, point, tri, bary = host
    idx = np.flatnonzero(active)
    kind = slots.kind[idx]
    t = np.flatnonzero(kind != 0)
    face = np.where(kind[t] == 1, slots.face[idx[t]], tri[idx[t]])
    tris = np.full((len(idx), 3), -1, np.int64)
    tris[t] = faces[face]
    w = np.zeros((len(idx), 3))
    w[t] = bary[idx[t]]
    return Contacts(slots.node[idx], slots.obj[idx], gap[idx], normal[idx], point[idx], tris, w)


@pytest.mark.parametrize("self_section", [True, False])
def test_collect_reads_the_slots_as_the_straightforward_form(self_section):
    rng = np.random.default_rng(4)
    surface = np.array([0, 2, 3, 5, 8, 9], np.int32)
    faces = np.array([[0, 2, 3], [2, 3, 5], [3, 5, 8], [5, 8, 9]], np.int32)
    ns, nf = len(surface), len(faces)
    sections = [Section(0, "node", 0, ns), Section(0, "face", ns, nf), Section(1, "node", ns + nf, ns)]
    if self_section:
        sections.append(Section(-1, "self", 2 * ns + nf, ns))
    n = sum(s.size for s in sections)

    class Topo:
        slot_map = SlotMap(sections, n, surface, faces)

    for density in (0.0, 0.3, 1.0):
        active = (rng.random(n) < density).astype(np.int32) * rng.integers(1, 4, n).astype(np.int32)
        host = [active, rng.standard_normal(n), rng.standard_normal((n, 3)), rng.standard_normal((n, 3)),
                rng.integers(0, nf, n).astype(np.int32), rng.random((n, 3))]
        got = collect(Topo, host)
        if not active.any():
            assert len(got) == 0
            continue
        ref = _collect_reference(Topo.slot_map, faces, host)
        for name in ("node", "obj", "gap", "normal", "point", "tri", "bary"):
            assert same_bits(getattr(got, name), getattr(ref, name)), name


def _solver(friction, object_friction):
    instruments = [{"name": f"tool{i}", "radius": 0.001, "length": 0.01, "friction": f}
                   for i, f in enumerate(object_friction)]
    return ContactSolver({"friction": friction}, instruments, [], "cpu", np.zeros((4, 3)))


@pytest.mark.parametrize("friction, object_friction, uniform", [
    (0.0, [None, None], True), (0.3, [None, 0.3], True), (0.0, [0.0, 0.2], False), (0.3, [None, 0.0], False),
    (0.0, [-0.0, None], False), (0.2, [], True)])
def test_friction_per_contact_is_the_objects_else_the_scenes(friction, object_friction, uniform):
    solver = _solver(friction, object_friction)
    obj = np.array([0, 1, -1, 1, 0, -1]) if object_friction else np.array([-1, -1])
    table = np.array([friction if f is None else f for f in object_friction] or [0.0])
    ref = np.where(obj >= 0, table[np.maximum(obj, 0)], friction)
    got = solver._friction(obj)
    assert got.uniform == uniform
    per_contact = np.full(len(obj), got.value) if got.uniform else got.per_contact
    assert same_bits(per_contact, ref)


def _names_reference(obj, node, tri, uids):
    names = np.full((len(node), 4), -1, np.int64)
    names[:, 0] = obj
    on_node = node >= 0
    names[on_node, 1] = uids[node[on_node]]
    names[~on_node, 1:] = np.sort(uids[tri[~on_node]], axis=1)
    return names


@pytest.mark.parametrize("faces", [0, 1, 5])
def test_contact_names_are_the_straightforward_ones(faces):
    rng = np.random.default_rng(5)
    uids = rng.permutation(50).astype(np.int64) + 100
    k = 8
    node = rng.integers(0, 50, k)
    node[:faces] = -1
    tri = np.full((k, 3), -1)
    tri[:faces] = rng.integers(0, 50, (faces, 3))
    tri[-2:] = rng.integers(0, 50, (2, 3))  # self-collision rows: a node and a triangle, named by the node
    obj = rng.integers(-1, 3, k)
    assert same_bits(contact_names(obj, node, tri, uids), _names_reference(obj, node, tri, uids))
    assert contact_names(obj[:0], node[:0], tri[:0], uids).shape == (0, 4)


def test_contacts_take_and_responded_are_the_field_by_field_forms():
    rng = np.random.default_rng(6)
    k = 6
    c = Contacts(rng.integers(-1, 9, k), rng.integers(-1, 2, k), rng.standard_normal(k), rng.standard_normal((k, 3)),
                 rng.standard_normal((k, 3)), rng.integers(-1, 9, (k, 3)), rng.random((k, 3)))
    mask = rng.random(k) < 0.5
    for rows in (mask, np.flatnonzero(mask)):
        got = c.take(rows)
        assert got.lambda_n is None and got.force is None
        for name, value in c.items():
            assert same_bits(getattr(got, name), value[rows])
    lam, force = rng.random(k), rng.standard_normal((k, 3))
    r = c.responded(lam, force)
    ref = dataclasses.replace(c, lambda_n=lam, force=force)
    assert all(getattr(r, f.name) is getattr(ref, f.name) for f in dataclasses.fields(Contacts))
    got = r.take(mask)
    assert same_bits(got.lambda_n, lam[mask]) and same_bits(got.force, force[mask])
    assert [name for name, _ in r.items()] == [f.name for f in dataclasses.fields(Contacts)]
    assert same_bits(r["gap"], c.gap)
    with pytest.raises(KeyError):
        r["nope"]


def _warm_reference(names, forces, kept, query):
    """The warm start as a dict built in row order (the last remembered row of a name wins)."""
    table = {tuple(n): f for n, f, k in zip(names.tolist(), forces, kept) if k}
    found = np.array([tuple(q) in table for q in query.tolist()], bool)
    return found, np.array([table[tuple(q)] for q, ok in zip(query.tolist(), found) if ok]).reshape(-1, 3)


@pytest.mark.parametrize("repeat", [False, True])
def test_warm_start_of_the_same_contacts_is_the_search(repeat):
    """A step whose contacts are the last step's, in order, takes their forces row by row only
    where the names are distinct; with a repeated name it searches (the last row wins)."""
    from soft_tissue_sim.contact.warm import WarmStart

    rng = np.random.default_rng(7)
    k = 9
    names = np.full((k, 4), -1, np.int64)
    names[:, 0] = rng.integers(-1, 2, k)
    names[:, 1] = rng.permutation(100)[:k]
    names[:3, 1:] = np.sort(rng.integers(0, 100, (3, 3)), axis=1)
    if repeat:
        names[6] = names[2]
    forces = rng.standard_normal((k, 3))
    kept = rng.random(k) < 0.6
    kept[[2, 6]] = [True, False]
    warm = WarmStart(names, forces, kept)
    assert len(warm) == kept.sum()
    for query in (names.copy(), names[::-1].copy(), names[:5].copy()):
        found, f = warm.lookup(query)
        ref_found, ref_f = _warm_reference(names, forces, kept, query)
        assert same_bits(found, ref_found) and same_bits(f, ref_f)
    # the next step's warm start, from the same contacts again: distinct names carry over
    query = names.copy()
    warm.lookup(query)
    forces2 = rng.standard_normal((k, 3))
    kept2 = ~kept
    nxt = warm.then(query, forces2, kept2)
    for q in (names.copy(), names[2:].copy()):
        found, f = nxt.lookup(q)
        ref_found, ref_f = _warm_reference(names, forces2, kept2, q)
        assert same_bits(found, ref_found) and same_bits(f, ref_f)
    other = warm.then(names.copy(), forces2, kept2)  # not the array looked up: distinctness not assumed
    assert same_bits(other.lookup(names)[1], _warm_reference(names, forces2, kept2, names)[1])
    assert not WarmStart().lookup(names)[0].any()
    assert not WarmStart(names, forces, np.zeros(k, bool)).lookup(names)[0].any()


def test_tangent_basis_is_the_straightforward_one():
    from soft_tissue_sim.contact.geometry import tangent_basis

    rng = np.random.default_rng(8)
    n = rng.standard_normal((40, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    n[:5] = [[1.0, 0.0, 0.0], [-0.9, np.sqrt(0.19), 0.0], [0.9 - 1e-12, 0.0, np.sqrt(1 - (0.9 - 1e-12) ** 2)],
             [np.nan, 0.0, 1.0], [0.0, 0.0, -1.0]]
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, a)
    t1 /= np.sqrt(np.einsum("ij,ij->i", t1, t1))[:, None]
    got = tangent_basis(n)
    assert same_bits(got[0], t1) and same_bits(got[1], np.cross(n, t1))
