"""The records the components add to a step's statistics (:class:`~soft_tissue_sim.
implicit_integration.StepStats`): the divergence guard's verdicts, the contact solve, the cuts.

Each is a dataclass of plain values; a field that is None did not apply to the step and is
left out of ``StepStats.as_dict()`` (so the keys there say what happened). Counters named in
the plural and ending in ``s`` with no unit (``rollbacks``, ``cuts``...) are running totals
since the scene started or was reset; the rest is this step's. Times in milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class GuardStats:
    """The divergence guard (NaN or runaway kinetic energy) in one step."""

    rolled_back: bool | None = None  # the free motion diverged and was rolled back
    rollbacks: int | None = None  # running total of rollbacks
    guard: str | None = None  # why it was rolled back
    remedy: str | None = None  # what stands instead: a retry that held, or the last good state
    contact_rejected: str | None = None  # why this step's contact correction was dropped
    contact_rejections: int | None = None  # running total of dropped corrections (scenes with contact)


@dataclass
class ContactStats:
    """One contact solve: detection, LCP (eq. 3) and correction."""

    contacts: int = 0  # constraints in the LCP (after dropping pairs that cannot touch)
    self_contacts: int = 0  # of which tissue against tissue
    face_contacts: int = 0  # of which an instrument against a tissue triangle
    active_contacts: int = 0  # with a positive normal force
    gs_iterations: int = 0  # Gauss-Seidel sweeps plus active-set steps (contact.pgs)
    lcp_residual: float = 0.0  # [m] largest change one more sweep would make
    max_penetration: float | None = 0.0  # [m] deepest penetration left after the correction (None: not
    # measured this step, see the contact option penetration_every)
    contact_ms: float = 0.0
    compliance: str | None = None  # the compliance W was built with (when there were contacts)
    compliance_fallbacks: int | None = None  # running total of fallbacks to the diagonal (idem)
    lcp_device: bool | None = None  # the LCP was solved on the device, with the correction
    lcp_redone: bool | None = None  # the device's solve was refused and redone on the host
    rows_device: bool | None = None  # the detection, rows, LCP and correction launched with the free motion


@dataclass
class CutStats:
    """The topology changes of one step (scripted cuts, the blade's sweep)."""

    cuts: int = 0  # running total of modifications
    tets_changed: int = 0
    affected_nodes: int = 0
    cut_ms: float = 0.0  # the step's cutting phase: planning, mesh change, correction, contact surface
    surface_ms: float = 0.0  # of which the contact surface's rebuild (scenes with contact)
    smf_u_ms: float = 0.0  # U = P^-1 G of the Sherman-Morrison correction (eq. 8)
    smf_q_ms: float = 0.0  # Q = (I + N S)^-1 N (eq. 9)
    # the cutting phase's parts, summed over the step's changes (CutResult's): planning, the
    # FEM, state and identities, the preconditioner's correction, the debris (found and planned
    # into the change); the rest of cut_ms (less surface_ms) is the state's reads and the
    # planning of what changed nothing
    plan_ms: float = 0.0
    apply_ms: float = 0.0
    correction_ms: float = 0.0
    debris_ms: float = 0.0


# CutStats' parts of cut_ms (besides surface_ms), with the names the benchmarks print them by
CUT_PARTS = {"plan_ms": "planning", "apply_ms": "FEM, state and identities", "correction_ms": "correction",
             "debris_ms": "debris"}
