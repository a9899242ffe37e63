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


def build_all(device) -> float:
    """Build all of Warp's loaded modules, the package's first (:func:`package_modules`), for
    ``device``. Returns the seconds the build took."""
    package_modules()
    t0 = time.perf_counter()
    wp.force_load(device=wp.get_device(device))
    return time.perf_counter() - t0
