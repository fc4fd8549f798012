# Do not run by hand: catkin_python_setup() in CMakeLists.txt calls it.
from __future__ import annotations

from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import setup

setup_args = generate_distutils_setup(
    packages=[
        "aruco_ring_localization",
        "aruco_ring_localization.ros",
        "aruco_ring_localization.simulation",
        "aruco_ring_localization.cli",
    ],
    package_dir={"": "src"},
)

setup(**setup_args)
