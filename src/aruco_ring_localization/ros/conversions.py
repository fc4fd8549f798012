"""Message <-> core conversions. The one place where ROS messages meet numpy.

Every function validates what comes in from a topic and raises
:class:`aruco_ring_localization.errors.MeasurementError` naming the topic field on bad input;
node callbacks catch it, log it throttled and go on.
"""
from __future__ import annotations

import math
from typing import Iterable, List, Optional, Sequence

import numpy as np
from fiducial_msgs.msg import Fiducial, FiducialArray
from geometry_msgs.msg import Pose, Quaternion, Transform, TransformStamped, Vector3
from sensor_msgs.msg import CameraInfo

from .. import geometry as geo
from ..camera import CameraModel
from ..errors import GeometryError, MeasurementError
from ..detections import CameraFrame, MarkerObservation


def stamp_to_sec(stamp) -> float:
    """rospy.Time / genpy.Time -> float seconds."""
    return float(stamp.secs) + 1e-9 * float(stamp.nsecs)


def fiducial_array_to_observations(msg: FiducialArray) -> List[MarkerObservation]:
    """FiducialArray -> observations (raw pixel corners in aruco_detect order).

    Values are copied as they are; use :func:`frames.sanitize_observations` to drop NaN or
    degenerate ones (so the count of rejected detections can be reported).
    """
    out = []
    for f in msg.fiducials:
        corners = np.array([[f.x0, f.y0], [f.x1, f.y1], [f.x2, f.y2], [f.x3, f.y3]], dtype=np.float64)
        out.append(MarkerObservation(int(f.fiducial_id), corners))
    return out


def fiducial_array_to_camera_frame(msg: FiducialArray, camera: str,
                                   model: Optional[CameraModel] = None) -> CameraFrame:
    """FiducialArray -> :class:`CameraFrame` of ring camera ``camera``."""
    return CameraFrame(camera=camera, stamp=stamp_to_sec(msg.header.stamp),
                       observations=fiducial_array_to_observations(msg), model=model)


def observations_to_fiducials(observations: Iterable[MarkerObservation]) -> List[Fiducial]:
    """Observations -> fiducial_msgs/Fiducial list (``direction`` is 0, as aruco_detect sets it)."""
    out = []
    for obs in observations:
        f = Fiducial()
        f.fiducial_id = int(obs.marker_id)
        f.direction = 0
        c = np.asarray(obs.corners, dtype=np.float64)
        f.x0, f.y0, f.x1, f.y1, f.x2, f.y2, f.x3, f.y3 = (float(v) for v in c.ravel())
        out.append(f)
    return out


def camera_info_to_model(msg: CameraInfo, name: str = "") -> CameraModel:
    """CameraInfo -> CameraModel; raises MeasurementError naming the field (K, D, width...)."""
    return CameraModel.from_camera_info(msg.K, msg.D, msg.distortion_model, msg.width, msg.height, name=name)


def model_to_camera_info(model: CameraModel, frame_id: str = "") -> CameraInfo:
    """CameraModel -> CameraInfo (R identity, P = [K | 0])."""
    msg = CameraInfo()
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(model.width), int(model.height)
    msg.distortion_model = model.distortion_model
    msg.D = [float(v) for v in model.D]
    msg.K = [float(v) for v in model.K.ravel()]
    msg.R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    P = np.zeros((3, 4))
    P[:3, :3] = model.K
    msg.P = [float(v) for v in P.ravel()]
    return msg


def transform_to_msg(T: np.ndarray) -> Transform:
    """4x4 -> geometry_msgs/Transform."""
    q = geo.quaternion_from_matrix(T)
    return Transform(translation=Vector3(*[float(v) for v in T[:3, 3]]), rotation=Quaternion(*[float(v) for v in q]))


def pose_to_msg(T: np.ndarray) -> Pose:
    """4x4 -> geometry_msgs/Pose."""
    q = geo.quaternion_from_matrix(T)
    p = Pose()
    p.position.x, p.position.y, p.position.z = (float(v) for v in T[:3, 3])
    p.orientation = Quaternion(*[float(v) for v in q])
    return p


def _vec(v, field: str) -> List[float]:
    values = [float(v.x), float(v.y), float(v.z)]
    if not all(math.isfinite(x) for x in values):
        raise MeasurementError(f"{field}: contains NaN or infinite values")
    return values


def _quat(q, field: str) -> List[float]:
    values = [float(q.x), float(q.y), float(q.z), float(q.w)]
    if not all(math.isfinite(x) for x in values):
        raise MeasurementError(f"{field}: contains NaN or infinite values")
    return values


def msg_to_transform(msg: Transform, field: str = "transform") -> np.ndarray:
    """geometry_msgs/Transform -> 4x4; raises MeasurementError naming ``field`` when invalid."""
    try:
        return geo.transform_from_translation_quaternion(_vec(msg.translation, f"{field}.translation"),
                                                         _quat(msg.rotation, f"{field}.rotation"))
    except GeometryError as exc:
        raise MeasurementError(f"{field}: {exc}") from None


def pose_msg_to_transform(msg: Pose, field: str = "pose") -> np.ndarray:
    """geometry_msgs/Pose -> 4x4; raises MeasurementError naming ``field`` when invalid."""
    try:
        return geo.transform_from_translation_quaternion(_vec(msg.position, f"{field}.position"),
                                                         _quat(msg.orientation, f"{field}.orientation"))
    except GeometryError as exc:
        raise MeasurementError(f"{field}: {exc}") from None


def make_transform_stamped(T: np.ndarray, parent: str, child: str, stamp) -> TransformStamped:
    """4x4 ``T_parent_child`` -> TransformStamped for tf."""
    ts = TransformStamped()
    ts.header.stamp = stamp
    ts.header.frame_id = parent
    ts.child_frame_id = child
    ts.transform = transform_to_msg(T)
    return ts


def se2_covariance_to_pose_covariance(cov3: np.ndarray, z_var: float = 1e6, rp_var: float = 1e6) -> List[float]:
    """(x, y, yaw) 3x3 covariance -> the 36 values of PoseWithCovariance (x y z roll pitch yaw order).

    z, roll and pitch are not estimated: they get a large variance so robot_localization ignores them
    (its ``two_d_mode`` users configure them out anyway).
    """
    C = np.zeros((6, 6))
    idx = [0, 1, 5]
    for a, i in enumerate(idx):
        for b, j in enumerate(idx):
            C[i, j] = cov3[a, b]
    C[2, 2] = z_var
    C[3, 3] = C[4, 4] = rp_var
    return [float(v) for v in C.ravel()]


def names_from_param(value, default: Sequence[str]) -> List[str]:
    """A list parameter given as a YAML list or as a comma/space separated string."""
    if value is None or value == "":
        return list(default)
    if isinstance(value, str):
        return [v for v in value.replace(",", " ").split() if v]
    return [str(v) for v in value]
