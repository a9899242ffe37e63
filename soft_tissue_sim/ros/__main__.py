"""``python -m soft_tissue_sim.ros``: run the node (``--ros-args`` accepted); exit code 1 on bad configuration."""

import sys

from .node import main

if __name__ == "__main__":  # not when a spawned worker process re-imports the main module
    sys.exit(main())
