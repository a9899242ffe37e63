"""ament_python package set-up (colcon build) and plain pip metadata.

``pip install -e .`` (what ``make install`` does, after requirements.txt) makes the library,
``python -m soft_tissue_sim.ros`` and the ``sim_node`` / ``soft_tissue_sim`` commands work
from any directory; scenes and meshes are then found in the checkout (config/, meshes/).
colcon installs them under share/soft_tissue_sim (data_files), found through the ament index.
The GPU libraries are the extra ``cuda`` (requirements-cuda.txt); ROS 2 itself (rclpy and the
message packages) comes from a ROS installation or the extra ``ros`` (the pip wheels of
requirements.txt). scikit-sparse builds against the system's SuiteSparse (libsuitesparse-dev).
"""

from glob import glob

from setuptools import find_packages, setup
from setuptools.command.develop import develop

package_name = "soft_tissue_sim"
# colcon build --symlink-install: console scripts under lib/<package> too (setup.cfg says why here)
options = {}
if any(o[0].rstrip("=").replace("-", "_") == "script_dir" for o in develop.user_options):
    options["develop"] = {"script_dir": "$base/lib/" + package_name}

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.rviz")),
        ("share/" + package_name + "/config/scenes", glob("config/scenes/*.yaml")),
        ("share/" + package_name + "/launch", glob("config/*.launch.py")),
        ("share/" + package_name + "/meshes", glob("meshes/*.vtu")),
    ],
    python_requires=">=3.10",
    install_requires=[  # the ranges of requirements.txt's pins
        "setuptools",
        "numpy>=2.4,<3",
        "scipy>=1.17,<2",
        "warp-lang>=1.19,<1.20",
        "meshio>=5.3,<6",
        "PyYAML>=6.0,<7",
        "matplotlib>=3.11,<4",
        "scikit-sparse>=0.4.16,<0.5",
    ],
    extras_require={
        "cuda": ["nvmath-python==1.0.0", "nvidia-cudss-cu13==0.8.*", "cupy-cuda13x"],  # = requirements-cuda.txt
        "ros": ["ros-jazzy-rclpy[fastrtps]==7.1.6", "ros-jazzy-common-interfaces==5.3.6"],
        "test": ["pytest"],
    },
    options=options,
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
