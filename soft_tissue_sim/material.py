"""Heterogeneous linear-elastic materials, Rayleigh damping and mass options.

A scene names materials by id; every tetrahedron carries a material id (see
:mod:`soft_tissue_sim.mesh`). This module validates the parameters and turns them
into per-element arrays (Lame coefficients and density) for the FEM kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


class ParameterError(ValueError):
    """A physical or numerical parameter is impossible (E <= 0, nu >= 0.5, dt <= 0, NaN...)."""


def _finite(name: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ParameterError(f"{name} must be finite, got {value!r}")
    return x


@dataclass(frozen=True)
class Material:
    """Isotropic linear-elastic material (small strain, used corotationally)."""

    young: float  # Young's modulus E [Pa]
    poisson: float  # Poisson ratio nu
    density: float  # [kg/m^3]
    name: str = ""

    def __post_init__(self):
        e = _finite(f"material {self.name!r} young", self.young)
        nu = _finite(f"material {self.name!r} poisson", self.poisson)
        rho = _finite(f"material {self.name!r} density", self.density)
        if e <= 0.0:
            raise ParameterError(f"material {self.name!r}: Young's modulus must be > 0, got {e}")
        if not -1.0 < nu < 0.5:
            raise ParameterError(
                f"material {self.name!r}: Poisson ratio must be in (-1, 0.5), got {nu} "
                "(0.5 is incompressible, which linear tetrahedra cannot represent)"
            )
        if rho <= 0.0:
            raise ParameterError(f"material {self.name!r}: density must be > 0, got {rho}")
        # store floats (YAML 1.1 reads "1.0e6" as a string)
        object.__setattr__(self, "young", e)
        object.__setattr__(self, "poisson", nu)
        object.__setattr__(self, "density", rho)

    @property
    def lame(self) -> tuple[float, float]:
        """(mu, lambda)."""
        e, nu = self.young, self.poisson
        mu = e / (2.0 * (1.0 + nu))
        lam = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        return mu, lam


@dataclass(frozen=True)
class Damping:
    """Rayleigh damping B = -(alpha M + beta K) (force = B v)."""

    mass: float = 0.0  # alpha [1/s]
    stiffness: float = 0.0  # beta [s]

    def __post_init__(self):
        for n, v in (("rayleigh mass", self.mass), ("rayleigh stiffness", self.stiffness)):
            if _finite(n, v) < 0.0:
                raise ParameterError(f"{n} damping must be >= 0, got {v}")


@dataclass
class MaterialTable:
    """Materials by id; maps per-element material ids to per-element arrays."""

    materials: dict[int, Material] = field(default_factory=dict)

    @classmethod
    def from_config(cls, items) -> "MaterialTable":
        """Build from a scene's ``materials`` list: ``[{id, young, poisson, density, name?}]``."""
        if not items:
            raise ParameterError("scene names no material")
        table = {}
        for k, it in enumerate(items):
            if not isinstance(it, dict):
                raise ParameterError(f"materials[{k}] must be a mapping, got {it!r}")
            mid = int(it.get("id", k))
            if mid in table:
                raise ParameterError(f"material id {mid} defined twice")
            missing = [key for key in ("young", "poisson", "density") if key not in it]
            if missing:
                raise ParameterError(f"materials[{k}] lacks {', '.join(missing)}")
            table[mid] = Material(it["young"], it["poisson"], it["density"], str(it.get("name", mid)))
        return cls(table)

    def element_arrays(self, material_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-element (mu, lambda, density) arrays, float64."""
        ids = np.asarray(material_ids)
        unknown = sorted(set(np.unique(ids).tolist()) - set(self.materials))
        if unknown:
            bad = np.flatnonzero(np.isin(ids, unknown))[:10].tolist()
            raise ParameterError(f"mesh uses material ids {unknown} that the scene does not define (cells {bad}...)")
        mu = np.empty(len(ids))
        lam = np.empty(len(ids))
        rho = np.empty(len(ids))
        for mid, mat in self.materials.items():
            sel = ids == mid
            mu[sel], lam[sel] = mat.lame
            rho[sel] = mat.density
        return mu, lam, rho

    def stiffness_ratio(self) -> float:
        es = [m.young for m in self.materials.values()]
        return max(es) / min(es)
