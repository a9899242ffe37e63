"""Benchmarks: ``python -m soft_tissue_sim.bench <name> [options]``.

Each benchmark writes JSON (device, date, git commit, figures) and PNG plots under
``benchmarks/results/`` (or ``--out``). Speed targets live here, never in tests.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from pathlib import Path

RESULTS_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def device_description(device: str) -> str:
    """A human name for the Warp device a benchmark ran on (GPU model or CPU model and cores)."""
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda:
        return f"{d.name} ({device})"
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"CPU: {cpu}, {os.cpu_count()} cores (warp cpu)"


def git_commit() -> str:
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "") if out.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def write_result(name: str, device: str, figures: dict, out_dir=None) -> Path:
    """Write ``<name>_<device-kind>.json`` with device, date and commit, and return its path."""
    out = Path(out_dir) if out_dir else RESULTS_DIR
    out.mkdir(parents=True, exist_ok=True)
    kind = "gpu" if str(device).startswith("cuda") else "cpu"
    path = out / f"{name}_{kind}.json"
    doc = {
        "benchmark": name,
        "device": device_description(device),
        "warp_device": str(device),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "figures": figures,
    }
    with open(path, "w") as fh:
        json.dump(doc, fh, indent=1, default=float)
    return path
