"""ros/conversions.py's quaternion on Python floats against geometry's (SciPy's): the same numbers.

Needs the built workspace (``source .ws/env.sh``: geometry_msgs, fiducial_msgs), no master.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import GeometryError
from aruco_ring_localization.ros.conversions import msg_to_transform, pose_msg_to_transform, pose_to_msg, \
    quaternion_xyzw, transform_to_msg


def _rotations():
    rng = np.random.default_rng(8)
    out = list(Rotation.random(3000, random_state=8).as_matrix())
    # each branch of the formula: the trace largest, or one of the diagonal terms; 180 deg turns
    out += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    out += [Rotation.from_rotvec(np.pi * a / np.linalg.norm(a)).as_matrix() for a in rng.normal(size=(50, 3))]
    out += [geo.transform_from_se2(0.0, 0.0, yaw)[:3, :3] for yaw in np.linspace(-np.pi, np.pi, 73)]
    return out


def test_quaternion_matches_geometry():
    for R in _rotations():
        T = np.eye(4)
        T[:3, :3] = R
        q = quaternion_xyzw(T)
        assert all(isinstance(v, float) for v in q) and q[3] >= 0.0
        np.testing.assert_allclose(q, geo.quaternion_from_matrix(T), rtol=0, atol=1e-15)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_quaternion_of_a_bad_matrix_raises_geometry_error(bad):
    T = np.eye(4)
    T[1, 2] = bad
    with pytest.raises(GeometryError, match="NaN or infinite"):
        quaternion_xyzw(T)


def test_pose_and_transform_messages_round_trip():
    for k, R in enumerate(_rotations()[:200]):
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [0.1 * k, -2.0, 0.3]
        np.testing.assert_allclose(pose_msg_to_transform(pose_to_msg(T)), T, atol=1e-12)
        np.testing.assert_allclose(msg_to_transform(transform_to_msg(T)), T, atol=1e-12)
