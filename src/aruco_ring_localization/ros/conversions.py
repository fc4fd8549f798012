"""Message <-> core conversions. The one place where ROS messages meet numpy.

Every function validates what comes in from a topic and raises
:class:`aruco_ring_localization.errors.MeasurementError` naming the topic field on bad input;
node callbacks catch it, log it throttled and go on.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Iterable, List, Optional, Tuple

import cv2
import genpy  # noqa: F401 - registers the "rosmsg" decoding error handler that message strings use
import numpy as np
from fiducial_msgs.msg import Fiducial, FiducialArray
from geometry_msgs.msg import Pose, Quaternion, Transform, TransformStamped, Vector3
from genpy import Time as rospy_time
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from .. import geometry as geo
from ..camera import CameraModel
from ..detection import image_to_gray
from ..detections import MarkerObservation
from ..errors import GeometryError, MeasurementError
from ..pipeline import pose_covariance_from_se2


def stamp_to_sec(stamp) -> float:
    """rospy.Time / genpy.Time -> float seconds."""
    return float(stamp.secs) + 1e-9 * float(stamp.nsecs)


def fiducial_array_to_observations(msg: FiducialArray, limit: Optional[int] = None) -> List[MarkerObservation]:
    """FiducialArray -> observations (raw pixel corners in aruco_detect order).

    Values are copied as they are; the pipeline sanitizes them (:func:`detections.sanitize_observations`)
    and counts what it drops (so the count of rejected detections can be reported). With ``limit``,
    only the first ``limit`` fiducials are converted (the pipeline refuses a message with more than
    ``input/max_detections``: converting 3,000 quads of a flood would be wasted work).
    """
    fiducials = msg.fiducials[:limit]
    if not fiducials:
        return []
    # One array for the message (each observation gets a row of it), not one numpy call per fiducial.
    corners = np.array([(f.x0, f.y0, f.x1, f.y1, f.x2, f.y2, f.x3, f.y3) for f in fiducials],
                       dtype=np.float64).reshape(-1, 4, 2)
    return [MarkerObservation(int(f.fiducial_id), c) for f, c in zip(fiducials, corners)]


#: One fiducial_msgs/Fiducial as serialised (little-endian, packed): int32 fiducial_id, int32
#: direction, float64 x0 y0 x1 y1 x2 y2 x3 y3.
FIDUCIAL_RECORD = np.dtype([("fiducial_id", "<i4"), ("direction", "<i4"), ("corners", "<f8", (8,))])
_HEADER = struct.Struct("<4I")   # header.seq, header.stamp.secs, header.stamp.nsecs, len(header.frame_id)
_TAIL = struct.Struct("<iI")     # image_seq, len(fiducials)


def _read_header(buff, after: int) -> Tuple[int, int, int, str, int]:
    """A serialised message's std_msgs/Header: (seq, secs, nsecs, frame_id, offset after it); at
    least ``after`` more bytes must follow. Raises :class:`MeasurementError` naming the field."""
    n_bytes = len(buff)
    if n_bytes < _HEADER.size:
        raise MeasurementError(f"header: message of {n_bytes} bytes is shorter than a header")
    seq, secs, nsecs, n_frame = _HEADER.unpack_from(buff, 0)
    pos = _HEADER.size + n_frame
    if n_bytes < pos + after:
        raise MeasurementError(f"header.frame_id: {n_frame} bytes announced, message of {n_bytes} bytes")
    return seq, secs, nsecs, bytes(buff[_HEADER.size:pos]).decode("utf-8", "rosmsg"), pos


def type_mismatch(msg, cls) -> Optional[str]:
    """None when the bytes ``msg`` (a ``rospy.AnyMsg``) are a ``cls`` (the publisher's md5sum), else
    what they are instead: "from <publisher> is '<type>', not <cls type>"."""
    header = getattr(msg, "_connection_header", None) or {}
    if header.get("md5sum") == cls._md5sum:
        return None
    return f"from {header.get('callerid', '?')} is {header.get('type', '?')!r}, not {cls._type}"


def camera_info_body(buff: bytes) -> bytes:
    """A serialised camera_info's bytes after its header's seq and stamp (the first 12): equal for
    two messages that differ only there (the intrinsics unchanged)."""
    return buff[12:]


def camera_info_from_bytes(buff: bytes) -> CameraInfo:
    """A serialised sensor_msgs/CameraInfo, deserialised; :class:`MeasurementError` when unreadable."""
    try:
        return CameraInfo().deserialize(buff)
    except (genpy.DeserializationError, struct.error, UnicodeDecodeError, ValueError) as exc:
        raise MeasurementError(f"unreadable camera_info ({len(buff)} bytes): {exc}") from exc


def fiducial_array_bytes_to_observations(buff: bytes, limit: Optional[int] = None
                                         ) -> Tuple[float, str, List[MarkerObservation]]:
    """A serialised fiducial_msgs/FiducialArray -> (header stamp s, header frame_id, observations).

    What :func:`fiducial_array_to_observations` gives for the deserialised message (the same
    ids and the same float64 corners, bit for bit; only the first ``limit`` fiducials), read
    with one ``numpy.frombuffer`` of the fixed-size fiducial records instead of a genpy object
    per fiducial. Raises :class:`MeasurementError` naming the field for a message cut short.
    """
    n_bytes = len(buff)
    _seq, secs, nsecs, frame_id, start = _read_header(buff, _TAIL.size)
    _image_seq, count = _TAIL.unpack_from(buff, start)
    start += _TAIL.size
    if n_bytes < start + count * FIDUCIAL_RECORD.itemsize:
        raise MeasurementError(f"fiducials: {count} announced ({count * FIDUCIAL_RECORD.itemsize} bytes), "
                               f"{n_bytes - start} bytes left in the message")
    stamp = float(secs) + 1e-9 * float(nsecs)
    k = count if limit is None else min(count, max(0, int(limit)))
    if k == 0:
        return stamp, frame_id, []
    records = np.frombuffer(buff, FIDUCIAL_RECORD, count=k, offset=start)
    corners = records["corners"].astype(np.float64).reshape(k, 4, 2)  # aligned, writable, native order
    return stamp, frame_id, [MarkerObservation(i, c) for i, c in zip(records["fiducial_id"].tolist(), corners)]


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


def quaternion_xyzw(T: np.ndarray) -> List[float]:
    """Unit quaternion [x, y, z, w] (w >= 0) of the rotation part of a 4x4 (or 3x3) matrix, as Python floats.

    :func:`geometry.quaternion_from_matrix` (SciPy's method: the largest of the trace and the
    diagonal picks the formula) on Python floats: 1 us instead of 10 us through SciPy, for the
    pose and the tf the localizer publishes per ring frame. A matrix with NaN or infinite values
    raises the same :class:`errors.GeometryError` as geometry's.
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(T, dtype=np.float64)[:3, :3].tolist()
    tr = m00 + m11 + m22
    if not math.isfinite(tr + m01 + m02 + m10 + m12 + m20 + m21):  # a NaN or inf (or a huge value): geometry's
        return [float(v) for v in geo.quaternion_from_matrix(T)]  # raises, naming the problem
    best = max(m00, m11, m22, tr)  # the first of these that is largest, as numpy's argmax
    if best == m00:
        q = [1.0 - tr + 2.0 * m00, m10 + m01, m20 + m02, m21 - m12]
    elif best == m11:
        q = [m01 + m10, 1.0 - tr + 2.0 * m11, m21 + m12, m02 - m20]
    elif best == m22:
        q = [m02 + m20, m12 + m21, 1.0 - tr + 2.0 * m22, m10 - m01]
    else:
        q = [m21 - m12, m02 - m20, m10 - m01, 1.0 + tr]
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[3] < 0.0:
        n = -n
    return [q[0] / n, q[1] / n, q[2] / n, q[3] / n]


def transform_to_msg(T: np.ndarray) -> Transform:
    """4x4 -> geometry_msgs/Transform."""
    x, y, z = T[:3, 3].tolist()
    return Transform(translation=Vector3(float(x), float(y), float(z)), rotation=Quaternion(*quaternion_xyzw(T)))


def pose_to_msg(T: np.ndarray) -> Pose:
    """4x4 -> geometry_msgs/Pose."""
    p = Pose()
    p.position.x, p.position.y, p.position.z = (float(v) for v in T[:3, 3].tolist())
    p.orientation = Quaternion(*quaternion_xyzw(T))
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
    """(x, y, yaw) 3x3 covariance -> the 36 values of PoseWithCovariance (x y z roll pitch yaw order);
    z, roll and pitch get a large variance (:func:`pipeline.pose_covariance_from_se2`)."""
    return [float(v) for v in pose_covariance_from_se2(cov3, z_var, rp_var).ravel()]


def image_msg_to_gray(msg) -> np.ndarray:
    """``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` -> (height, width) mono8 array.

    The one image decoder of the package (the detector node and the bag source use it).

    * Image: :func:`detection.image_to_gray` (mono8/8UC1, mono16/16UC1 scaled by 1/256, bgr8, rgb8,
      bgra8, rgba8; padding, byte order and short buffers checked, errors name the field).
    * CompressedImage (``format`` "jpeg", "png", "mono8; jpeg compressed bgr8", ...):
      ``cv2.imdecode``, then the same grey conversion as the raw encodings (a PNG gives exactly
      the raw image's pixels).

    Why not Debian's cv_bridge (python3-cv-bridge): it does load with the venv's NumPy 1.26.4 and
    gives the same pixels for mono8, bgr8 and compressed png/jpeg (mono16 within one grey level),
    but ``compressed_imgmsg_to_cv2(msg, "mono8")`` fails on single-channel compressed images (it
    converts BGR to grey whatever was decoded), its errors do not name the bad field, and it would
    pull about 140 Debian packages (a second OpenCV, GDAL, ffmpeg) into every install for what
    ``np.frombuffer`` and ``cv2.imdecode`` do here.

    Raises:
        MeasurementError: naming the field (``encoding``, ``width/height``, ``step``, ``data``).
    """
    if not hasattr(msg, "encoding"):  # sensor_msgs/CompressedImage: header, format, data
        data = msg.data
        buf = data.reshape(-1).view(np.uint8) if isinstance(data, np.ndarray) else np.frombuffer(bytes(data), np.uint8)
        if buf.size == 0:
            raise MeasurementError("data: empty compressed image")
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if img is None or img.size == 0:
            raise MeasurementError(f"data: cannot decode the compressed image (format {msg.format!r})")
        # The same grey as the raw encodings' (cv2.IMREAD_GRAYSCALE's own conversion differs by a level).
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(img)
    return image_to_gray(msg.encoding, msg.width, msg.height, msg.step, msg.data,
                         is_bigendian=bool(getattr(msg, "is_bigendian", 0)))


@dataclass
class ImageBytes:
    """A serialised ``sensor_msgs/Image`` read in place: the fields :func:`image_msg_to_gray` and
    the detector use, with ``data`` a zero-copy view of the message's bytes (read-only)."""

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview


_U32 = struct.Struct("<I")
_STEP = struct.Struct("<BI")  # is_bigendian, step


def image_bytes_to_msg(buff: bytes) -> ImageBytes:
    """A serialised sensor_msgs/Image -> :class:`ImageBytes`, without copying the pixels.

    What rospy's own deserialisation gives (the same header and fields), but ``data`` is a view of
    ``buff`` instead of a 1.2 MB copy of a 1280x960 bgr8 image's bytes (one copy of four that
    rospy makes between the socket and the callback). Raises :class:`MeasurementError` naming the
    field for a message cut short.
    """
    mv = memoryview(buff)
    n_bytes = len(mv)
    seq, secs, nsecs, frame_id, pos = _read_header(mv, 12)
    header = Header(seq=seq, stamp=rospy_time(secs, nsecs), frame_id=frame_id)
    height, width, n_enc = struct.unpack_from("<3I", mv, pos)
    pos += 12
    if n_bytes < pos + n_enc + _STEP.size + _U32.size:
        raise MeasurementError(f"encoding: {n_enc} bytes announced, {n_bytes - pos} bytes left in the message")
    encoding = bytes(mv[pos:pos + n_enc]).decode("utf-8", "rosmsg")
    pos += n_enc
    is_bigendian, step = _STEP.unpack_from(mv, pos)
    pos += _STEP.size
    (n_data,) = _U32.unpack_from(mv, pos)
    pos += _U32.size
    if n_bytes < pos + n_data:
        raise MeasurementError(f"data: {n_data} bytes announced, {n_bytes - pos} bytes left in the message")
    return ImageBytes(header=header, height=int(height), width=int(width), encoding=encoding,
                      is_bigendian=int(is_bigendian), step=int(step), data=mv[pos:pos + n_data])
