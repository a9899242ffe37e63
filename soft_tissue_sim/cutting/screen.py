"""The blade's sweep screened where the body's state lives (``split``): which interior faces a
sweep cuts, found by a kernel on the device's own positions and read back as one mask.

While the pedal is down the blade is planned every step, and most sweeps change nothing: they
cross no face, or the faces they cross separate nothing yet. On the host such a plan first
reads the whole state back and culls the tets with NumPy. :class:`SweepScreen` finds the faces
on the device (:func:`sweep_faces_kernel`: the test of :func:`.geometry.faces_cut_kernel` on
every tet, against its box, its plane and its faces, with the same functions); the cutter then
reads the state only for a sweep that separates something.

Invariants: a face's answer is the host kernel's arithmetic on the same positions (its tet's
nodes, the centroids of the face's two tets), built without fused multiply-adds on any device,
so the mask is :func:`.geometry.faces_cut_by_triangles`' on the same positions. The positions
and tets are the body's own device arrays; the mesh's face tables go to the device once per
mesh (at the first screen after a change), the blade's triangles through a pinned buffer
without a wait; a face is marked with the screen's number, so the mask is never cleared.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..mesh import TetMesh
from ..transfer import Staged, to_host
from .geometry import _centroid_side, _near_and_across, _parts_cut

# no gradients are taken; no fused multiply-add, so that a GPU's answer is the host's bit for bit
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

MAX_TRIANGLES = 4  # a blade's sweep is two; more (a scripted patch) is planned on the host


@wp.func
def _side_of(x: wp.array(dtype=wp.vec3d), tet: wp.vec4i, a: wp.vec3d, n: wp.vec3d):
    """:func:`.geometry._centroid_side` of the tet ``tet`` at the positions ``x``."""
    return _centroid_side(x[tet[0]], x[tet[1]], x[tet[2]], x[tet[3]], a, n)


@wp.kernel
def sweep_faces_kernel(x: wp.array(dtype=wp.vec3d), tets: wp.array(dtype=wp.vec4i),
                       blade: wp.array2d(dtype=wp.vec3d), tol: wp.float64, tet_face: wp.array(dtype=wp.vec4i),
                       pairs: wp.array(dtype=wp.vec2i), stamp: wp.int32, cut: wp.array(dtype=wp.int32)):
    """For the tet t and the blade triangle k (``blade[k]``: its vertices a, b, c and unit
    normal n): where its box meets the triangle's (widened by ``tol``), its vertices lie on both
    sides of the plane (+tol), one of its interior faces lies between tets on opposite sides of
    the plane (their centroids) and its section by the plane overlaps the triangle, those faces
    are cut: cut[face] = ``stamp``, this screen's number (so that no zeroing comes before it).
    :func:`.geometry.faces_cut_kernel` on every tet."""
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
    if not _near_and_across(X0, X1, X2, X3, a, b, c, n, tol):
        return
    faces = tet_face[t]
    parts = wp.vec4i(0, 0, 0, 0)  # the tet's interior faces between tets on opposite sides
    for q in range(4):
        f = faces[q]
        if f >= 0:  # (nested: the pair is read only for a face)
            pr = pairs[f]
            if _side_of(x, tets[pr[0]], a, n) != _side_of(x, tets[pr[1]], a, n):
                parts[q] = 1
    if _parts_cut(X0, X1, X2, X3, a, b, c, n, tol, parts):
        for q in range(4):
            if parts[q] != 0:
                cut[faces[q]] = stamp


class SweepScreen:
    """The faces a blade's sweep cuts, found on ``device`` (:func:`sweep_faces_kernel`) from the
    positions and tets kept there. :meth:`faces_cut` returns the mask over
    ``mesh.interior_faces()``. Per mesh: its face tables on the device, a mask and a recorded
    launch; per sweep: the blade's copy, the launch with the next stamp, and the mask's read."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._blade = Staged((MAX_TRIANGLES, 4), wp.vec3d, self.device)
        self._mesh = None  # the mesh whose face tables are on the device
        self._faces = None  # those tables (tet_face, pairs), which the recorded launch reads
        self._cut = None  # the mask (the stamp of the last screen that cut each face)
        self._launch = None  # the kernel's launch on them, recorded
        self._args = None  # (x, tets, dim) the launch holds
        self._stamp = 0

    def _prepare(self, mesh: TetMesh, x: wp.array, tets: wp.array, dim: tuple):
        if self._mesh is not mesh:
            pairs, _, tet_face = mesh.interior_faces()
            d = self.device
            self._faces = (wp.array(np.ascontiguousarray(tet_face, np.int32), dtype=wp.vec4i, device=d),
                           wp.array(np.ascontiguousarray(pairs, np.int32), dtype=wp.vec2i, device=d))
            self._cut = wp.zeros(len(pairs), dtype=wp.int32, device=d)
            self._stamp = 0
            self._launch = wp.launch(sweep_faces_kernel, dim, [x, tets, self._blade.array, 0.0, *self._faces, 0,
                                                               self._cut], device=d, record_cmd=True)
            self._mesh, self._args = mesh, (x, tets, dim)
        held_x, held_tets, held_dim = self._args
        if x is not held_x:
            self._launch.set_param_by_name("x", x)
        if tets is not held_tets:
            self._launch.set_param_by_name("tets", tets)
        if dim != held_dim:
            self._launch.set_dim(dim)
        self._args = (x, tets, dim)
        if self._stamp >= np.iinfo(np.int32).max:
            self._cut.zero_()
            self._stamp = 0
        self._stamp += 1
        return self._launch

    def faces_cut(self, x: wp.array, tets: wp.array, mesh: TetMesh, tris: np.ndarray, normals: np.ndarray,
                  tol: float):
        """The mask (bool, one per interior face of ``mesh``) of the faces the blade triangles
        ``tris`` (T, 3, 3; non-degenerate, with unit ``normals``) cut, on the positions ``x`` and
        the tets ``tets`` (vec4i, ``mesh.tets`` on this screen's device); None for more than
        :data:`MAX_TRIANGLES` triangles (the host plans those)."""
        T = len(tris)
        if T > MAX_TRIANGLES:
            return None
        launch = self._prepare(mesh, x, tets, (mesh.n_tets, T))
        if not len(self._cut):  # no interior face: nothing to cut
            return np.zeros(0, bool)
        host = self._blade.view()
        host[:T, :3] = tris
        host[:T, 3] = normals
        self._blade.send(4 * T)
        launch.set_param_by_name("tol", float(tol))
        launch.set_param_by_name("stamp", self._stamp)
        launch.launch()
        return to_host(self._cut)[0] == self._stamp
