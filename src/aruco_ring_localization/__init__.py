"""aruco_ring_localization: map ArUco markers and localize a robot with a ring of calibrated cameras.

The core modules (everything except :mod:`aruco_ring_localization.ros`) import no ROS package and
work with numpy arrays: 4x4 poses named ``T_<to>_<from>``, pixels, metres and radians.
"""
from __future__ import annotations

__version__ = "0.1.0"
