"""Test set-up: keep DDS discovery on this machine before any rclpy.init()."""

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# Arrays made without a device go where the suite's scenes are (Warp's CPU backend) even on a
# machine with a GPU, where Warp's default device would be cuda:0; tests of the device
# (STS_TEST_DEVICE) name theirs.
import warp as wp  # noqa: E402

wp.set_device("cpu")
