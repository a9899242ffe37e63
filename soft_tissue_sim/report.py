"""Live progress line and summary table for runs of many steps (CLI, demo, benchmarks)."""

from __future__ import annotations

import sys
import time

import numpy as np


class Progress:
    """A one-line progress bar on a terminal (plain periodic lines when not a TTY)."""

    def __init__(self, total: int, stream=None, every_s: float = 0.25):
        self.total = max(int(total), 1)
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.every_s = every_s if self.tty else 2.0
        self._last = 0.0
        self.t0 = time.perf_counter()

    def update(self, done: int, text: str = "") -> None:
        now = time.perf_counter()
        if done < self.total and now - self._last < self.every_s:
            return
        self._last = now
        frac = done / self.total
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        line = f"[{bar}] {done}/{self.total} {now - self.t0:6.1f}s {text}"
        if self.tty:
            self.stream.write("\r" + line + ("\n" if done >= self.total else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def summarize(stats: list[dict]) -> dict:
    """Aggregate per-step statistics (dicts from StepStats.as_dict())."""
    if not stats:
        return {"steps": 0}
    col = lambda k: np.array([s.get(k, 0.0) or 0.0 for s in stats], dtype=float)  # noqa: E731
    total = col("total_ms")
    it = col("iterations")
    out = {
        "steps": len(stats),
        "total_ms_mean": float(total.mean()),
        "total_ms_p50": float(np.percentile(total, 50)),
        "total_ms_p99": float(np.percentile(total, 99)),
        "build_ms_mean": float(col("build_ms").mean()),
        "solve_ms_mean": float(col("solve_ms").mean()),
        "iterations_mean": float(it.mean()),
        "iterations_max": int(it.max()),
        "residual_max": float(col("residual").max()),
        "not_converged": int(sum(1 for s in stats if not s.get("converged", True))),
        "fps": float(1000.0 / total.mean()) if total.mean() > 0 else float("inf"),
    }
    if any("contacts" in s for s in stats):
        out["contacts_max"] = int(col("contacts").max())
    for k in ("cuts", "rollbacks"):  # running totals kept by the simulation: the last value counts
        if any(k in s for s in stats):
            out[k + "_total"] = int(max(s.get(k, 0) or 0 for s in stats))
    return out


def table(rows: list[tuple[str, object]], title: str = "") -> str:
    """A two-column text table."""
    w = max(len(k) for k, _ in rows) if rows else 0
    lines = [title, "-" * max(len(title), w + 20)] if title else []
    for k, v in rows:
        if isinstance(v, float):
            v = f"{v:.4g}"
        lines.append(f"{k:<{w}}  {v}")
    return "\n".join(lines)
