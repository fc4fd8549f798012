"""``detector`` node: ArUco detection on one camera, a drop-in for UbiquityRobotics' aruco_detect.

Subscribes (relative names, so one node per camera namespace, e.g. ``ring/cam0``):
    ``image`` (sensor_msgs/Image; mono8, mono16, bgr8, rgb8, bgra8, rgba8), or with
        ``~image_transport: compressed`` ``image/compressed`` (sensor_msgs/CompressedImage, JPEG or
        PNG; image_transport's name): queue_size 1 and a large socket buffer, so a detector that
        falls behind drops old images, never queues them. Raw images are subscribed as bytes
        (rospy.AnyMsg, the publisher's type checked) and read in place: the pixels are a view of
        the received bytes, not a copy in a message object;
    ``camera_info`` (sensor_msgs/CameraInfo, also as bytes): intrinsics for the poses (latest valid
        one wins), deserialised only when its bytes after the stamp change.
Publishes:
    ``fiducial_vertices`` (fiducial_msgs/FiducialArray): one per usable image, header = the
        image's header (frame_id falls back to camera_info's when the image has none),
        ``image_seq`` = the image's seq; EMPTY when no marker is seen (the localizer relies on it
        to know the camera is alive). Corners in aruco_detect order, raw pixels.
    ``fiducial_transforms`` (fiducial_msgs/FiducialTransformArray, when ``do_pose_estimation``
        and intrinsics are known): per-marker ``T_camera_marker`` in the image's optical frame
        with aruco_detect's ``image_error``, ``object_error``, ``fiducial_area``
        (:class:`aruco_ring_localization.detection.MarkerPose`).
    ``fiducial_images`` (sensor_msgs/Image bgr8, when ``publish_images``): annotated image.

Parameters (private, read once; aruco_detect's names): :class:`aruco_ring_localization.schemas.DetectorConfig`
(config/detector.yaml, docs/parameters.md).

Bad input never stops the node: an unusable image (unsupported encoding, zero size, wrong step
or data length) or camera_info (missing, all-zero K, bad D) gives ONE warning per problem per
``WARN_PERIOD`` seconds naming the field, and the next good message is processed normally.
The logic is in :class:`DetectorCore` (no rospy; messages are duck-typed); the bag source
(:mod:`ros.bag_source`) runs it on recorded images.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence

import genpy
import numpy as np
from std_msgs.msg import Header

from ..camera import CameraModel
from ..detection import Detector, MarkerPose, TrackingDetector, annotate, marker_poses
from ..detections import MarkerObservation
from ..errors import ArucoRingError, ConfigError, MeasurementError
from ..schemas import DetectorConfig
from ..throttle import ThrottledWarnings
from .conversions import (camera_info_body, camera_info_from_bytes, image_bytes_to_msg, image_msg_to_gray,
                          type_mismatch)

logger = logging.getLogger(__name__)

#: Seconds between two warnings about the same problem.
WARN_PERIOD = 10.0
#: Socket buffer of the image subscription: several 1280x960 bgr8 images (four; thirteen mono8),
#: so rospy never reads a frame in pieces (a small buff_size makes rospy fall behind and deliver
#: stale images). Below glibc's largest mmap threshold (32 MB, threads.tune_malloc), so the buffer
#: is heap memory reused from read to read: with 64 MB each read was a fresh mmap whose pages the
#: kernel zeroed as the image came in (0.63 against 0.31 ms CPU per 1.2 MB image read).
IMAGE_BUFF_SIZE = 1 << 24


@dataclass
class Detections:
    """What one image gives.

    Attributes:
        header: the image's header (stamp, seq; ``frame_id`` filled from camera_info if empty).
        observations: markers kept (ignored ids removed), raw pixels.
        poses: their poses, or None when not estimated (off, or no intrinsics).
        annotated: (H, W, 3) uint8 BGR image, or None unless ``publish_images``.
    """

    header: object
    observations: List[MarkerObservation]
    poses: Optional[List[MarkerPose]]
    annotated: Optional[np.ndarray] = None


def _field_key(exc: MeasurementError) -> str:
    """``encoding`` from ``"encoding: unsupported ..."`` (the field the error names)."""
    head = str(exc).split(":", 1)[0].strip()
    return head if head and " " not in head else "other"


class DetectorCore:
    """The detector node's logic, without rospy: feed it messages, get detections to publish.

    Args:
        params: the node's parameters (validated here: raises ConfigError naming the key).
        warn: sink of warning lines (throttled here per problem); default this module's logger.
        name: label used in the warnings (the node's namespace).
        clock: monotonic seconds for the throttling.
    """

    def __init__(self, params: DetectorConfig, warn: Optional[Callable[[str], None]] = None,
                 name: str = "detector", clock: Callable[[], float] = time.monotonic):
        self.params = params
        # Regions around the previous image's markers between whole-image searches (detection.py).
        self.detector = TrackingDetector(Detector(params.detector_params()), full_every=params.tracking_full_every,
                                         edge_px=params.tracking_edge_px,
                                         windows_in_turn=params.tracking_windows_in_turn)
        self.sizes = params.sizes()
        self.ignored = params.ignored()
        self.name = name
        self.warnings = ThrottledWarnings(warn if warn is not None else logger.warning, WARN_PERIOD, clock=clock)
        self.model: Optional[CameraModel] = None
        self.camera_frame_id = ""
        self._info_key: Optional[tuple] = None
        self.images = 0          # images processed
        self.dropped_stale = 0   # images dropped by max_image_age
        self.rejected_images = 0  # unusable images

    # --- camera_info ---------------------------------------------------------------------------

    def on_camera_info(self, msg) -> bool:
        """Take the intrinsics of a ``sensor_msgs/CameraInfo`` (the latest valid one wins); False
        when it was unusable (warned about, throttled)."""
        try:
            K = np.asarray(msg.K, dtype=np.float64)
            if K.size != 9 or not np.any(K):
                raise MeasurementError("K: all zeros (uncalibrated camera); poses need a calibration")
            key = (tuple(K.ravel()), tuple(np.asarray(msg.D, dtype=np.float64).ravel()), str(msg.distortion_model),
                   int(msg.width), int(msg.height))
            if key != self._info_key:
                self.model = CameraModel.from_camera_info(K, msg.D, msg.distortion_model, msg.width, msg.height,
                                                          name=self.name)
                self._info_key = key
            self.camera_frame_id = str(msg.header.frame_id)
            return True
        except MeasurementError as exc:
            self.warnings(f"camera_info.{_field_key(exc)}", f"{self.name}: camera_info ignored: {exc}")
        except (ArucoRingError, TypeError, ValueError) as exc:
            self.warnings("camera_info.other", f"{self.name}: camera_info ignored: {exc}")
        return False

    # --- image ---------------------------------------------------------------------------------

    def on_image(self, msg, now: Optional[float] = None, want_poses: bool = True,
                 want_image: bool = True) -> Optional[Detections]:
        """Detect markers in a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``.

        Args:
            msg: the image message (header, encoding, width, height, step, data, is_bigendian; or
                header, format, data).
            now: current ROS time, s (only for ``max_image_age``).
            want_poses: estimate the poses (when ``do_pose_estimation``); the node passes False
                while nobody subscribes to ``fiducial_transforms`` (the ring's localizer and mapper
                use the vertices): the poses were 10-15 % of the node's CPU.
            want_image: draw the annotated image (when ``publish_images``).

        Returns:
            :class:`Detections` to publish, or None when the image was unusable or stale (a
            throttled warning says why; nothing should be published for it).
        """
        header = msg.header
        if self.params.max_image_age > 0.0 and now is not None:
            age = now - (float(header.stamp.secs) + 1e-9 * float(header.stamp.nsecs))
            if age > self.params.max_image_age:
                self.dropped_stale += 1
                self.warnings("image.stale", f"{self.name}: dropped {self.dropped_stale} stale image(s) "
                                             f"({age:.2f} s old > max_image_age {self.params.max_image_age} s)")
                return None
        try:
            gray = image_msg_to_gray(msg)
            observations = self.detector.detect(gray)
        except MeasurementError as exc:
            self.rejected_images += 1
            self.warnings(f"image.{_field_key(exc)}", f"{self.name}: image ignored: {exc}")
            return None
        self.images += 1
        if self.ignored:
            observations = [o for o in observations if o.marker_id not in self.ignored]
        if not header.frame_id and self.camera_frame_id:
            header.frame_id = self.camera_frame_id
        poses = self._poses(observations, gray.shape) if want_poses else None
        annotated = annotate(gray, observations, poses or (), self.model) \
            if self.params.publish_images and want_image else None
        return Detections(header=header, observations=observations, poses=poses, annotated=annotated)

    def _poses(self, observations: Sequence[MarkerObservation], shape) -> Optional[List[MarkerPose]]:
        if not self.params.do_pose_estimation:
            return None
        if self.model is None:
            self.warnings("camera_info.missing", f"{self.name}: no usable camera_info yet: publishing "
                                                 "fiducial_vertices only, no fiducial_transforms")
            return None
        if (self.model.height, self.model.width) != tuple(shape):
            self.warnings("camera_info.size", f"{self.name}: image is {shape[1]}x{shape[0]} but camera_info "
                                              f"says {self.model.width}x{self.model.height}: no poses")
            return None
        return marker_poses(observations, self.model, self.sizes)


# --- ROS adapter -----------------------------------------------------------------------------------

def _header_copy(header):
    """A new std_msgs/Header with the same seq, stamp and frame_id (copy.deepcopy's result, in a
    tenth of its time)."""
    return Header(seq=header.seq, stamp=genpy.Time(header.stamp.secs, header.stamp.nsecs),
                  frame_id=header.frame_id)


def fiducial_array_msg(det: Detections):
    """FiducialArray of one image's detections."""
    from fiducial_msgs.msg import FiducialArray

    from .conversions import observations_to_fiducials

    out = FiducialArray()
    out.header = _header_copy(det.header)  # rospy's publish() rewrites header.seq in place
    out.image_seq = int(det.header.seq)
    out.fiducials = observations_to_fiducials(det.observations)
    return out


def fiducial_transform_array_msg(det: Detections):
    """FiducialTransformArray of one image's marker poses (``det.poses`` must not be None)."""
    from fiducial_msgs.msg import FiducialTransform, FiducialTransformArray

    from .conversions import transform_to_msg

    out = FiducialTransformArray()
    out.header = _header_copy(det.header)
    out.image_seq = int(det.header.seq)
    for p in det.poses or ():
        ft = FiducialTransform()
        ft.fiducial_id = int(p.marker_id)
        ft.transform = transform_to_msg(p.T_cam_marker)
        ft.image_error = float(p.image_error)
        ft.object_error = float(p.object_error)
        ft.fiducial_area = float(p.fiducial_area)
        out.transforms.append(ft)
    return out


def image_msg(bgr: np.ndarray, header):
    """sensor_msgs/Image (bgr8) from an (H, W, 3) uint8 array."""
    from sensor_msgs.msg import Image

    out = Image()
    out.header = _header_copy(header)
    out.height, out.width = int(bgr.shape[0]), int(bgr.shape[1])
    out.encoding = "bgr8"
    out.is_bigendian = 0
    out.step = int(bgr.shape[1] * 3)
    out.data = np.ascontiguousarray(bgr).tobytes()
    return out


class DetectorNode:
    """Publishers/subscribers around a :class:`DetectorCore` (needs ``rospy.init_node`` first)."""

    def __init__(self, params: DetectorConfig):
        import rospy
        from fiducial_msgs.msg import FiducialArray, FiducialTransformArray
        from sensor_msgs.msg import CompressedImage, Image

        self.rospy = rospy
        self.core = DetectorCore(params, warn=rospy.logwarn, name=rospy.get_namespace().rstrip("/") or "detector")
        self.vertices_pub = rospy.Publisher("fiducial_vertices", FiducialArray, queue_size=5)
        self.transforms_pub = (rospy.Publisher("fiducial_transforms", FiducialTransformArray, queue_size=5)
                               if params.do_pose_estimation else None)
        self.image_pub = rospy.Publisher("fiducial_images", Image, queue_size=1) if params.publish_images else None
        # camera_info and raw images as bytes (rospy.AnyMsg), type-checked here: camera_info is
        # deserialised only when it changed (it comes with every image), and the image's pixels are
        # used in place (conversions.image_bytes_to_msg) instead of copied into a message object.
        self._info_body: Optional[bytes] = None
        self.info_sub = rospy.Subscriber("camera_info", rospy.AnyMsg, self.on_camera_info_bytes, queue_size=1)
        # image_transport's naming: the compressed stream of <image> is <image>/compressed.
        if params.image_transport == "compressed":
            self.image_sub = rospy.Subscriber("image/compressed", CompressedImage, self.on_image, queue_size=1,
                                              buff_size=IMAGE_BUFF_SIZE, tcp_nodelay=True)
        else:
            self.image_sub = rospy.Subscriber("image", rospy.AnyMsg, self.on_image_bytes, queue_size=1,
                                              buff_size=IMAGE_BUFF_SIZE, tcp_nodelay=True)

    def _of_type(self, msg, cls, topic: str) -> bool:
        """Whether the bytes ``msg`` on ``topic`` are a ``cls`` (the publisher's md5sum); else a
        throttled warning naming the publisher and its type, and False."""
        wrong = type_mismatch(msg, cls)
        if wrong is None:
            return True
        self.core.warnings(f"{topic}.type", f"{self.core.name}: {topic} {wrong}: ignored")
        return False

    def on_camera_info_bytes(self, msg) -> None:
        """camera_info as bytes: handed to the core (deserialised) only when it changed; the bytes
        after the header's seq and stamp are compared, so a new stamp alone is no change."""
        from sensor_msgs.msg import CameraInfo

        body = camera_info_body(msg._buff)
        if body == self._info_body or not self._of_type(msg, CameraInfo, "camera_info"):
            return
        try:
            info = camera_info_from_bytes(msg._buff)
        except MeasurementError as exc:
            self.core.warnings("camera_info.other", f"{self.core.name}: {exc}")
            return
        self._info_body = body if self.core.on_camera_info(info) else None

    def on_image_bytes(self, msg) -> None:
        """A raw image as bytes: type-checked, read in place, handled as :meth:`on_image`."""
        from sensor_msgs.msg import Image

        if not self._of_type(msg, Image, "image"):
            return
        try:
            image = image_bytes_to_msg(msg._buff)
        except MeasurementError as exc:
            self.core.rejected_images += 1
            self.core.warnings(f"image.{_field_key(exc)}", f"{self.core.name}: image ignored: {exc}")
            return
        self.on_image(image)

    def on_image(self, msg) -> None:
        rospy = self.rospy
        try:
            # Poses and annotated images only for someone who listens (rospy drops unsent messages,
            # but only after we paid for them).
            det = self.core.on_image(
                msg, now=rospy.get_time(),
                want_poses=self.transforms_pub is not None and self.transforms_pub.get_num_connections() > 0,
                want_image=self.image_pub is not None and self.image_pub.get_num_connections() > 0)
            if det is None:
                return
            self.vertices_pub.publish(fiducial_array_msg(det))
            if self.transforms_pub is not None and det.poses is not None:
                self.transforms_pub.publish(fiducial_transform_array_msg(det))
            if self.image_pub is not None and det.annotated is not None:
                self.image_pub.publish(image_msg(det.annotated, det.header))
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"detector: image skipped: {exc}")
        except rospy.ROSException as exc:  # publishing during shutdown
            rospy.logdebug("detector: %s", exc)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the node until shutdown; 1 on a bad parameter (fatal log naming it)."""
    import rospy

    from ..threads import limit_threads, tune_malloc
    from . import log_bridge
    from .params import read_config

    limit_threads()  # one BLAS / OpenCV thread: 8 detectors share the cores (threads.py)
    tune_malloc()    # the image buffer from the heap, not a fresh mmap per read (threads.py)
    rospy.init_node("detector", argv=list(argv) if argv is not None else None)
    log_bridge.install()
    try:
        params = read_config(DetectorConfig)
        node = DetectorNode(params)
    except ConfigError as exc:
        rospy.logfatal("detector: bad parameter: %s", exc)
        return 1
    p = node.core.params
    rospy.loginfo("detector: dictionary %d, fiducial_len %.3f m, corner refinement %s, pose estimation %s, "
                  "image transport %s", p.dictionary, p.fiducial_len, p.corner_refinement,
                  "on" if p.do_pose_estimation else "off", p.image_transport)
    rospy.spin()
    return 0
