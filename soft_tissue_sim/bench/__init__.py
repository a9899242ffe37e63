"""Benchmarks: ``python -m soft_tissue_sim.bench <name> [options]``.

Each benchmark writes a JSON result (device, date, git commit, figures) and a PNG under
``benchmarks/results/`` (or ``--out``); :mod:`.common` holds what they share. Speed targets
live here, never in tests.
"""

from .common import RESULTS_DIR, write_result

__all__ = ["RESULTS_DIR", "write_result"]
