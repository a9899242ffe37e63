"""Test set-up: keep DDS discovery on this machine before any rclpy.init()."""

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
