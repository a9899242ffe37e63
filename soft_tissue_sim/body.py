"""What the components read of the simulated body at a step.

:class:`~soft_tissue_sim.scene.Simulation` builds a :class:`BodyView` for each step and hands it
to the contact solver; the components read through it and return what they change (a
correction, a topology change), which the Simulation applies. The view holds references, not
copies: a component must not write through it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .corotational_fem import CorotationalFEM
    from .implicit_integration import BackwardEuler


@dataclass(frozen=True)
class BodyView:
    """The body during a step: state, dynamics and the preconditioner of eq. (1)."""

    integrator: BackwardEuler  # state x, v (after the free motion), dt, A = m_coef M + k_coef K, its PCG
    fem: CorotationalFEM  # mesh, fixed nodes, element blocks, rotations
    preconditioner: object  # P ~ A: its factor gives the contact compliance (eq. 4)
    node_uids: np.ndarray  # node identities that survive topology changes
