"""``python -m soft_tissue_sim.bench <benchmark> [options]``: runs soft_tissue_sim.bench.<benchmark>."""

import importlib
import sys

BENCHMARKS = {
    "solvers": "solvers",  # error against run time for every solver (issue: async LDL^T)
    "accuracy": "accuracy",  # error against run time over all solvers and scenes
    "cut-beam": "cut_beam",  # the paper's cut beam table and the SMF overhead
    "stability": "stability",  # extreme cases, every solver
    "brain": "brain",  # brain tumour resection end to end
    "profile": "profile",  # where the time of one step goes (kernels, copies, host)
    "scaling": "scaling",  # cost against mesh size
    "haptic": "haptic",  # step time distribution: CG, CG in a graph, CHOLMOD, dense, cuDSS
    "workers": "workers",  # the async factorization in a thread or in worker processes
    "backends": "backends",  # the factor backends (cholmod, dense, cudss) against body size
    "targets": "targets",  # every target row, one table and targets_<cpu|gpu>.json
    "node": "node",  # the ROS node driven from another process as a robot stack would
    "lcp": "lcp",  # the contact LCP's host and device solvers on recorded problems
}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in BENCHMARKS:
        print(f"usage: python -m soft_tissue_sim.bench {{{'|'.join(BENCHMARKS)}}} [options]", file=sys.stderr)
        return 2
    mod = importlib.import_module(f"soft_tissue_sim.bench.{BENCHMARKS[argv[0]]}")
    return mod.main(argv[1:]) or 0


if __name__ == "__main__":
    sys.exit(main())
