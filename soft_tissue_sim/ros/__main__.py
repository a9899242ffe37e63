"""``python -m soft_tissue_sim.ros``: run the node (``--ros-args`` accepted)."""

from .node import main

main()
