"""ament_python package set-up (colcon build) and plain pip metadata."""

from glob import glob

from setuptools import find_packages, setup

package_name = "soft_tissue_sim"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.rviz")),
        ("share/" + package_name + "/config/scenes", glob("config/scenes/*.yaml")),
        ("share/" + package_name + "/launch", glob("config/*.launch.py")),
        ("share/" + package_name + "/meshes", glob("meshes/*.vtu")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="soft_tissue_sim developers",
    maintainer_email="dev@soft-tissue-sim.local",
    description="Real-time soft-tissue surgical simulator on Warp with a ROS 2 node",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "soft_tissue_sim = soft_tissue_sim.__main__:main",
            "sim_node = soft_tissue_sim.ros.node:main",
        ],
    },
)
