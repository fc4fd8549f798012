# Do not run by hand: catkin_python_setup() in CMakeLists.txt calls it.
# Packages: aruco_ring_localization and its subpackages (.ros, .simulation, .cli, ...), found
# under src/ so that a new subpackage needs no edit here.
from __future__ import annotations

from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import find_packages, setup

setup_args = generate_distutils_setup(
    packages=find_packages("src", include=["aruco_ring_localization", "aruco_ring_localization.*"]),
    package_dir={"": "src"},
)

setup(**setup_args)
