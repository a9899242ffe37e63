"""Timings the benchmarks share: one application of a preconditioner, and a run of steps."""

from __future__ import annotations

import time

import numpy as np
import warp as wp


def apply_timing(sim, reps: int = 50) -> dict:
    """ms per application of the simulation's preconditioner at its current state (after a
    ``begin_step``): launched from Python and synchronised (``apply_ms``) and, where the
    application can be captured on CUDA, replayed in a graph of 10 (``graph_apply_ms``)."""
    pre = sim.preconditioner
    dev = wp.get_device(sim.device)
    n = sim.mesh.n_nodes
    r = wp.array(np.random.default_rng(0).standard_normal((n, 3)), dtype=wp.vec3d, device=dev)
    z = wp.zeros_like(r)
    pre.apply(r, z)
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    for _ in range(reps):
        pre.apply(r, z)
    wp.synchronize_device(dev)
    out = {"apply_ms": 1000.0 * (time.perf_counter() - t0) / reps}
    if dev.is_cuda and getattr(pre, "graph_key", lambda: None)() is not None:
        with wp.ScopedCapture(device=dev) as cap:
            for _ in range(10):
                pre.apply(r, z)
        wp.capture_launch(cap.graph)
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        for _ in range(reps):
            wp.capture_launch(cap.graph)
        wp.synchronize_device(dev)
        out["graph_apply_ms"] = 1000.0 * (time.perf_counter() - t0) / (10 * reps)
    return out


def timed_steps(sim, steps: int, before=None) -> tuple[list[float], list]:
    """Wall ms of ``steps`` calls of ``sim.step()`` and their statistics; ``before(k)`` runs
    ahead of step k, outside the timing (instrument poses, say)."""
    walls, stats = [], []
    for k in range(steps):
        if before is not None:
            before(k)
        t0 = time.perf_counter()
        st = sim.step()
        walls.append(1000.0 * (time.perf_counter() - t0))
        stats.append(st)
    return walls, stats


def refresh_timing(sim, repeats: int = 3) -> float:
    """Median wall ms of a new factor of the current state (assembly, factorization, install)."""
    pre, integ = sim.preconditioner, sim.integrator
    dev = wp.get_device(sim.device)
    walls = []
    for _ in range(repeats):
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        pre.refresh(integ)
        wp.synchronize_device(dev)
        walls.append(1000.0 * (time.perf_counter() - t0))
    return float(np.median(walls))
