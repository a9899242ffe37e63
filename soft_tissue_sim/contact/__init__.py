"""Contact by Lagrange multipliers with the preconditioner's compliance (paper section 2.3,
eq. 3-4; with cuts, eq. 11-12).

After the free motion of eq. (1), the contacts found on it give the LCP

    delta = W lambda + delta^0,   0 <= delta_n  _|_  lambda_n >= 0,   |lambda_t| <= mu lambda_n,
    W = dt^2 H P^-1 H^T,          x += dt^2 P^-1 H^T lambda,          v += (that) / dt

with H the contacts' Jacobian (normal rows, and two tangent rows with friction) and P the
step's preconditioner (approximately A of eq. 1). Invariants: lambda_n >= 0 and the friction
force within its cone; lambda is a force ON THE TISSUE [N] (not an impulse); fixed nodes
never move (their columns of H are zero); an object's wrench is the force ON the object.

Modules: :mod:`.geometry` (closest points, Warp functions), :mod:`.detection_kernels` and
:mod:`.detection` (what touches what), :mod:`.records` (:class:`Contacts`), :mod:`.compliance`
(W), :mod:`.pgs` (the LCP), :mod:`.options` (the scene's ``contact`` keys), :mod:`.solver`
(:class:`ContactSolver`, the component a scene builds when it names instruments, obstacles or
self-collision).
"""

from .records import Contacts
from .solver import ContactSolver

__all__ = ["ContactSolver", "Contacts"]
