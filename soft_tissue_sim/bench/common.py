"""What every benchmark shares: its command line, its result file and its figure.

A result is ``<results>/<name>_<cpu|gpu>.json``: the benchmark, the device (in words and as
Warp names it), the date, the git commit and the figures. Figures are summaries, plus the
short per-step arrays a plot needs (:func:`columns`); the full per-step records go in only
with ``--detail`` (they make files of megabytes). The PNG beside it is drawn from the same
figures, so a file can be plotted again.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
from pathlib import Path

RESULTS_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def parser(name: str, doc: str | None, device: str | None = None) -> argparse.ArgumentParser:
    """The benchmark's command line with the options they all have: --device, --out, --detail."""
    ap = argparse.ArgumentParser(prog=f"python -m soft_tissue_sim.bench {name}", description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=device, help="cpu | cuda | cuda:N (default: CUDA if present)")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of the result files")
    ap.add_argument("--detail", action="store_true", help="also write the per-step records into the JSON")
    return ap


def resolved_device(args) -> str:
    """The Warp device ``--device`` names (ParameterError where there is none such)."""
    from ..scene import resolve_device

    return resolve_device(args.device)


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
    """The checkout's short commit (``-dirty`` with uncommitted changes); ``STS_COMMIT`` names it
    where the code runs from a copy whose git state is not its own."""
    if os.environ.get("STS_COMMIT"):
        return os.environ["STS_COMMIT"]
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "") if out.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def _round(v, digits: int):
    if isinstance(v, float) and math.isfinite(v) and v != 0.0:
        return round(v, digits - 1 - int(math.floor(math.log10(abs(v)))))
    return v


def rounded(values, digits: int = 5) -> list:
    """A per-step series for a plot, floats to ``digits`` significant digits (a small JSON)."""
    return [_round(v, digits) for v in values]


def columns(rows: list[dict], keys, digits: int = 5) -> dict[str, list]:
    """Per-step arrays for a plot, one :func:`rounded` list per key: a few tens of kilobytes
    where the records they come from take megabytes."""
    return {k: rounded([r.get(k) for r in rows], digits) for k in keys}


def write_result(name: str, device: str, figures: dict, out_dir=None, detail: dict | None = None) -> Path:
    """Write ``<name>_<cpu|gpu>.json`` (device, date, commit, figures; ``detail`` merged into the
    figures when given) and return its path."""
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
        "figures": figures | (detail or {}),
    }
    with open(path, "w") as fh:
        json.dump(doc, fh, indent=1, default=float)
    return path


def figure(nrows: int = 1, ncols: int = 1, **kwargs):
    """(figure, axes) of matplotlib on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(nrows, ncols, **kwargs)


def save_figure(fig, prefix: str, title: str) -> Path:
    """Title, lay out and write ``<prefix>.png``; the figure is closed."""
    import matplotlib.pyplot as plt

    fig.suptitle(title)
    fig.tight_layout()
    path = Path(f"{prefix}.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def publish(name: str, device: str, figures: dict, args, plot=None, detail: dict | None = None) -> Path:
    """Write the result (``detail`` only with ``--detail``) and, with ``plot(figures, prefix)``,
    the PNG beside it (``figures["device"]`` set for its title); print where. Returns the JSON's
    path."""
    path = write_result(name, device, figures, args.out, detail if getattr(args, "detail", False) else None)
    if plot is None:
        print(f"wrote {path}")
        return path
    plot(figures | {"device": device_description(device)}, str(path.with_suffix("")))
    print(f"wrote {path} and {path.with_suffix('.png')}")
    return path
