"""The scene's ``contact`` options: defaults and validation.

Scene options (all optional)::

    contact:
      distance: 0.002        # [m] detection distance: pairs closer than this become constraints
      friction: 0.0          # Coulomb coefficient (obstacles / instruments may set their own)
      friction_cone: disk    # disk | pyramid
      max_iterations: 200    # Gauss-Seidel sweeps plus active-set steps
      tolerance: 1.0e-8      # [m] LCP residual (largest W_rr |change of lambda_r| in a sweep)
      active_set: true       # a frictionless LCP: finish the sweeps by an exact active-set
                             # method (contact.pgs); false: sweeps only
      friction_active_set: auto  # an LCP with friction: finish the sweeps by an active-set
                             # method on the contacts' states (contact.pgs; on the device, the
                             # LCP's block, contact.device_lcp); needs active_set. auto: on the
                             # CPU, not on a GPU (one lane's finish costs a GPU step more than
                             # the sweeps it saves)
      self_collision: false  # tissue surface nodes against the tissue's own triangles
      facing: 0.5            # same-component self contact only if n_node . n_triangle <= -facing
      self_depth: null       # [m] deepest penetration behind a tissue triangle taken as real
                             # (default 2 x distance); deeper is the far side of the body
      compliance: preconditioner   # preconditioner | diagonal | exact (see contact.compliance)
      max_contacts: 2048     # keep the deepest ones beyond this
      device_lcp_rows: 32    # with a dense factor: solve an LCP of up to this many rows on the
                             # device, with the correction (0: always on the host)
      device_rows: true      # with the device LCP and no mesh obstacle: build its (tangent too)
                             # rows on the device too, so that the detection, the LCP and the
                             # correction follow the free motion in the same read (false: rows
                             # built on the host from the read detection)
      penetration_every: 1   # measure the deepest penetration left after the correction (a
                             # detection at the corrected positions) every this many steps
                             # (0: never); unmeasured steps report max_penetration None

:func:`friction_finish_on` says where the friction finish runs.

Invariant: :func:`parse_options` returns every key of :data:`DEFAULTS`, validated, or raises
:class:`~soft_tissue_sim.material.ParameterError` with a message.
"""

from __future__ import annotations

from ..instrument import finite_number
from ..material import ParameterError

COMPLIANCES = ("preconditioner", "diagonal", "exact")
DEFAULTS = {
    "distance": 0.002,
    "friction": 0.0,
    "friction_cone": "disk",
    "max_iterations": 200,
    "tolerance": 1e-8,
    "active_set": True,
    "friction_active_set": "auto",
    "self_collision": False,
    "facing": 0.5,
    "self_depth": None,
    "compliance": "preconditioner",
    "max_contacts": 2048,
    "device_lcp_rows": 32,
    "device_rows": True,
    "penetration_every": 1,
}


def parse_options(cfg) -> dict:
    """The contact options of a scene, defaults filled in."""
    if not isinstance(cfg, dict):
        raise ParameterError(f"scene 'contact' must be a mapping, got {cfg!r}")
    unknown = set(cfg) - set(DEFAULTS)
    if unknown:
        raise ParameterError(f"contact: unknown keys {sorted(unknown)} (allowed: {sorted(DEFAULTS)})")
    o = {**DEFAULTS, **{k: v for k, v in cfg.items() if v is not None}}
    o["distance"] = finite_number("contact distance", o["distance"], minimum=0.0, strict=True)
    o["friction"] = finite_number("contact friction", o["friction"], minimum=0.0)
    o["tolerance"] = finite_number("contact tolerance", o["tolerance"], minimum=0.0, strict=True)
    o["facing"] = finite_number("contact facing", o["facing"], minimum=-1.0)
    if o["facing"] > 1.0:
        raise ParameterError(f"contact facing is a cosine in [-1, 1], got {o['facing']}")
    o["self_depth"] = (2.0 * o["distance"] if o["self_depth"] is None
                       else finite_number("contact self_depth", o["self_depth"], minimum=0.0, strict=True))
    every = o["penetration_every"]
    if isinstance(every, bool) or not isinstance(every, int) or every < 0:
        raise ParameterError(f"contact penetration_every must be an integer >= 0, got {every!r}")
    for key in ("max_iterations", "max_contacts"):
        if isinstance(o[key], bool) or not isinstance(o[key], int) or o[key] < 1:
            raise ParameterError(f"contact {key} must be an integer >= 1, got {o[key]!r}")
    rows = o["device_lcp_rows"]
    if isinstance(rows, bool) or not isinstance(rows, int) or not 0 <= rows <= 256:
        raise ParameterError(f"contact device_lcp_rows must be an integer in [0, 256], got {rows!r}")
    for key in ("self_collision", "active_set", "device_rows"):
        if not isinstance(o[key], bool):
            raise ParameterError(f"contact {key} must be true or false, got {o[key]!r}")
    if not isinstance(o["friction_active_set"], bool) and o["friction_active_set"] != "auto":
        raise ParameterError("contact friction_active_set must be true, false or auto, got "
                             f"{o['friction_active_set']!r}")
    if o["friction_cone"] not in ("disk", "pyramid"):
        raise ParameterError(f"contact friction_cone must be 'disk' or 'pyramid', got {o['friction_cone']!r}")
    if o["compliance"] not in COMPLIANCES:
        raise ParameterError(f"contact compliance must be one of {', '.join(COMPLIANCES)}, got {o['compliance']!r}")
    return o


def friction_finish_on(options: dict, gpu: bool) -> bool:
    """Whether an LCP with friction is finished by the active-set method (``friction_active_set``
    with ``active_set``) in a simulation on a GPU (``gpu``) or on the CPU. ``auto`` finishes
    them on the CPU only: on a GPU the device's block solves the small sets, where the finish
    costs more than it saves, and the host's solves of the larger ones follow suit (sweeps
    started from finished forces crawl: a run keeps one kind)."""
    asked = options["friction_active_set"]
    return bool(options["active_set"]) and (asked is True or (asked == "auto" and not gpu))
