"""soft_tissue_sim: real-time soft-tissue simulation (corotational FEM, backward Euler,
asynchronous LDL^T preconditioner, cutting and contact) on Warp, with a ROS 2 node.

The solver core imports nothing from rclpy; :mod:`soft_tissue_sim.ros` adapts it to ROS 2.
"""

from .implicit_integration import StepStats
from .material import ParameterError
from .mesh import MeshError, TetMesh, load_mesh
from .realtime import freeze_long_lived
from .scene import Simulation, load_scene

__all__ = ["load_scene", "Simulation", "StepStats", "TetMesh", "load_mesh", "MeshError", "ParameterError",
           "freeze_long_lived"]
__version__ = "0.1.0"
