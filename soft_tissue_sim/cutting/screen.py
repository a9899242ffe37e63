"""The blade's sweep screened where the body's state lives (``split``): which interior faces a
sweep cuts, found by a kernel on the device's own positions and read back as one mask.

While the pedal is down the blade is planned every step, and most sweeps change nothing: they
cross no face, or the faces they cross separate nothing yet. On the host such a plan first reads
the whole state back and culls the tets with NumPy. :class:`SweepScreen` answers the first
question on the device (:func:`sweep_faces_kernel`: the test of
:func:`.geometry.faces_cut_kernel` on every tet, each against its box, its plane and its faces,
with the same functions), and the cutter reads the state only for a sweep that cuts something.

Invariants: a face's answer is the host kernel's arithmetic on the same positions (its tet's
nodes, the centroids of the face's two tets), built without fused multiply-adds on any device,
so the mask is :func:`.geometry.faces_cut_by_triangles`' on the same positions; the mesh's tables go to the device once per mesh (the next screen after a
change), the blade's triangles through a pinned buffer without a wait.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..mesh import TetMesh
from ..transfer import Staged, to_host
from .geometry import _dot3, _section_meets

# no gradients are taken; no fused multiply-add, so that a GPU's answer is the host's bit for bit
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

MAX_TRIANGLES = 16  # a blade's sweep is two; more (a scripted patch) is planned on the host


@wp.func
def _centroid_side(x: wp.array(dtype=wp.vec3d), tet: wp.vec4i, a: wp.vec3d, n: wp.vec3d):
    """Whether the tet's centroid (its nodes summed in order, over 4) is on the positive side of
    the plane through a with normal n (or on it): :func:`.geometry._side`."""
    s = x[tet[0]] + x[tet[1]]
    s = s + x[tet[2]]
    s = s + x[tet[3]]
    return _dot3(s / wp.float64(4.0) - a, n) >= wp.float64(0.0)


@wp.kernel
def sweep_faces_kernel(x: wp.array(dtype=wp.vec3d), tets: wp.array(dtype=wp.vec4i),
                       blade: wp.array2d(dtype=wp.vec3d), tol: wp.float64, tet_face: wp.array(dtype=wp.vec4i),
                       pairs: wp.array(dtype=wp.vec2i), cut: wp.array(dtype=wp.int32)):
    """For the tet t and the blade triangle k (``blade[k]``: its vertices a, b, c and unit
    normal n): where its box meets the triangle's (widened by ``tol``), its vertices lie on both
    sides of the plane (+tol), one of its interior faces lies between tets on opposite sides of
    the plane (their centroids) and its section by the plane overlaps the triangle, those faces
    are cut (cut[face] = 1): :func:`.geometry.faces_cut_kernel` on every tet."""
    t, k = wp.tid()
    tet = tets[t]
    X0 = x[tet[0]]
    X1 = x[tet[1]]
    X2 = x[tet[2]]
    X3 = x[tet[3]]
    a = blade[k, 0]
    b = blade[k, 1]
    c = blade[k, 2]
    n = blade[k, 3]
    for ax in range(3):
        lo = wp.min(wp.min(a[ax], b[ax]), c[ax]) - tol
        hi = wp.max(wp.max(a[ax], b[ax]), c[ax]) + tol
        if X0[ax] < lo and X1[ax] < lo and X2[ax] < lo and X3[ax] < lo:
            return
        if X0[ax] > hi and X1[ax] > hi and X2[ax] > hi and X3[ax] > hi:
            return
    d0 = _dot3(X0 - a, n)
    d1 = _dot3(X1 - a, n)
    d2 = _dot3(X2 - a, n)
    d3 = _dot3(X3 - a, n)
    if not (wp.min(wp.min(d0, d1), wp.min(d2, d3)) <= tol and wp.max(wp.max(d0, d1), wp.max(d2, d3)) >= -tol):
        return
    faces = tet_face[t]
    parts = wp.vec4i(0, 0, 0, 0)
    some = int(0)
    for q in range(4):
        f = faces[q]
        if f >= 0:
            pr = pairs[f]
            if _centroid_side(x, tets[pr[0]], a, n) != _centroid_side(x, tets[pr[1]], a, n):
                parts[q] = 1
                some = 1
    if some == 0:
        return
    if _section_meets(X0, X1, X2, X3, a, b, c, n, tol):
        for q in range(4):
            if parts[q] != 0:
                cut[faces[q]] = 1


class SweepScreen:
    """The faces a blade's sweep cuts, found on ``device`` (:func:`sweep_faces_kernel`) from the
    positions kept there. :meth:`faces_cut` returns the mask over ``mesh.interior_faces()``."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._blade = Staged((MAX_TRIANGLES, 4), wp.vec3d, self.device)
        self._mesh = None  # the mesh whose tables are on the device
        self._tables = None  # (tets, tet_face, pairs, cut) there

    def _tables_for(self, mesh: TetMesh):
        if self._mesh is not mesh:
            pairs, _, tet_face = mesh.interior_faces()
            d = self.device
            self._tables = (wp.array(np.ascontiguousarray(mesh.tets, np.int32), dtype=wp.vec4i, device=d),
                            wp.array(np.ascontiguousarray(tet_face, np.int32), dtype=wp.vec4i, device=d),
                            wp.array(np.ascontiguousarray(pairs, np.int32), dtype=wp.vec2i, device=d),
                            wp.zeros(len(pairs), dtype=wp.int32, device=d))
            self._mesh = mesh
        return self._tables

    def faces_cut(self, x: wp.array, mesh: TetMesh, tris: np.ndarray, normals: np.ndarray, tol: float):
        """The mask (bool, one per interior face of ``mesh``) of the faces the blade triangles
        ``tris`` (T, 3, 3; non-degenerate, with unit ``normals``) cut, on the positions ``x``
        (``mesh``'s nodes, on this screen's device); None for more than :data:`MAX_TRIANGLES`
        triangles (the host plans those)."""
        T = len(tris)
        if T > MAX_TRIANGLES:
            return None
        tets, tet_face, pairs, cut = self._tables_for(mesh)
        if not len(pairs) or not T:
            return np.zeros(len(pairs), bool)
        host = self._blade.view()
        host[:T, :3] = tris
        host[:T, 3] = normals
        blade = self._blade.send(4 * T)
        cut.zero_()
        wp.launch(sweep_faces_kernel, (mesh.n_tets, T), [x, tets, blade, float(tol), tet_face, pairs, cut],
                  device=self.device)
        return to_host(cut)[0].astype(bool)
