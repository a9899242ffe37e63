"""ROS 2 adapter (rclpy) over the solver core: the ``soft_tissue_sim`` node."""
