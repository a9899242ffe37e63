"""Every Warp kernel module of the package built for a device at once.

Warp builds a module (or loads it from its kernel cache) at the first launch of one of its
kernels. With a warm cache that costs a few milliseconds; on a machine that has not built
this version of the package yet it is a compilation, tens of seconds for the contact modules
on a GPU. Left to the first launch, it lands in the middle of a run: the first contact step of
a node stalls, its wrenches stop and its service calls time out. :func:`build_all` does all of
it up front (the node calls it at start-up; ``bench targets`` before its first row).
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time

import warp as wp


def package_modules() -> list[str]:
    """Import every module of the package that may hold Warp code (not the ROS adapter, not the
    benchmarks; a module whose optional GPU library is missing is skipped: nothing uses it
    then); returns their names."""
    import soft_tissue_sim

    names = []
    for mod in pkgutil.walk_packages(soft_tissue_sim.__path__, "soft_tissue_sim."):
        if ".ros" in mod.name or ".bench" in mod.name:
            continue
        try:
            importlib.import_module(mod.name)
        except ImportError:
            continue
        names.append(mod.name)
    return names


def cpu_only(name: str) -> bool:
    """Whether the imported module ``name`` says its kernels run on Warp's CPU device alone (a
    module-level ``WARP_CPU_ONLY = True``: the host's LCP, the blade's geometry)."""
    return bool(getattr(sys.modules.get(name), "WARP_CPU_ONLY", False))


def build_all(device) -> float:
    """Build all of Warp's loaded modules, the package's first (:func:`package_modules`), for
    ``device``, but the package's modules whose kernels run on the CPU alone (:func:`cpu_only`)
    for the CPU, where they run. Returns the seconds the build took."""
    host = [name for name in package_modules() if cpu_only(name)]
    t0 = time.perf_counter()
    wp.force_load(device=wp.get_device(device), modules=[m for m in _warp_modules() if m.name not in host])
    wp.force_load(device="cpu", modules=[wp.get_module(name) for name in host])
    return time.perf_counter() - t0


def _warp_modules() -> list:
    """Every loaded Warp module (the package's and Warp's own), as ``wp.force_load`` takes them
    by default."""
    from warp._src.context import user_modules

    return list(user_modules.values())
