"""ROS input of the ring: per-camera detections + camera_info + tf -> ring frames.

Shared by the mapper and the localizer. Usage, inside a node after ``rospy.init_node``::

    ring_input = RingInput(ring, camera_names, on_ring_frame, slop=0.03, timeout=0.25)
    ...
    def on_ring_frame(frame: RingFrame) -> None:
        ring = ring_input.ring                        # extrinsics in force (tf, cached)
        for name, cam_frame in frame.cameras.items():
            model = cam_frame.model                   # intrinsics from that camera's camera_info
            T_base_cam = ring[name].T_base_cam

For each camera ``c`` (a ring camera name) it subscribes to ``<ns>/fiducial_vertices``
(fiducial_msgs/FiducialArray) and ``<ns>/camera_info`` (sensor_msgs/CameraInfo), where ``<ns>`` is
the camera's ``namespace`` in the ring file (relative, so a node's namespace applies).

* Intrinsics: the latest camera_info, converted once per change. Without one the camera is
  skipped (throttled warning) unless ``camera_info_fallback`` uses the ring file's.
* Extrinsics: ``T_base_cam`` looked up in tf once for the frame_id of the detections' header
  (``ring.base_frame`` -> ``header.frame_id``; the ring's frame_id when the header is empty),
  then cached. Until tf has it, the camera is skipped (throttled warning). ``use_tf=False``
  uses the ring file's extrinsics.
* Malformed detections (NaN corners, degenerate quads, duplicate ids in one image, ignored ids)
  are dropped and counted (:attr:`rejected`), with a throttled warning.
* A timer polls the assembler, so a silent camera never stalls the others: its group goes out
  after ``timeout`` seconds without it (listed in ``RingFrame.missing``).

``on_ring_frame`` is called from one thread at a time, in stamp order; exceptions of the package
(:class:`ArucoRingError`) raised by it are caught and logged throttled, so a bad frame never
kills the node.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Callable, Collection, Dict, List, Optional, Sequence, Tuple

import numpy as np
import rospy
import tf2_ros
from fiducial_msgs.msg import FiducialArray
from sensor_msgs.msg import CameraInfo

from ..errors import ArucoRingError
from ..detections import RingFrame
from ..ring import CameraRing
from ..detections import SKIP_NO_CAMERA_INFO, SKIP_NO_EXTRINSICS, RingInputCore
from .conversions import camera_info_to_model, fiducial_array_to_observations, msg_to_transform, stamp_to_sec

WARN_PERIOD = 5.0  # s between repeats of one throttled warning


def resolve_camera_names(ring: CameraRing, entries: Optional[Sequence[str]]) -> List[str]:
    """Ring camera names from a parameter listing names (``cam0``) or namespaces (``ring/cam0``).

    Empty -> every ring camera. Raises ValueError naming an entry that matches nothing.
    """
    if not entries:
        return ring.names
    by_ns = {c.namespace.strip("/"): c.name for c in ring.cameras}
    out = []
    for e in entries:
        e = str(e).strip()
        if e in ring.names:
            out.append(e)
        elif e.strip("/") in by_ns:
            out.append(by_ns[e.strip("/")])
        else:
            raise ValueError(f"camera {e!r} is neither a ring camera name {ring.names} nor a namespace "
                             f"{sorted(by_ns)}")
    return out


class RingInput:
    """Subscribe to the ring's cameras and deliver assembled ring frames.

    Args:
        ring: calibrated ring (camera names, namespaces, frames; fallback intrinsics/extrinsics).
        camera_names: ring camera names to use (None or empty: all).
        on_ring_frame: called with each :class:`RingFrame`.
        slop: stamps within this (s) form one ring frame.
        timeout: an incomplete group goes out this long (s, wall clock) after its first member.
        use_tf: extrinsics from tf (True) or from the ring file (False).
        camera_info_fallback: use the ring file's intrinsics while a camera has no camera_info.
        ignore_ids: marker ids never passed on.
        poll_period: period (s) of the timer that flushes timed-out groups.
        tf_buffer: an existing tf2 Buffer to share (one with a listener is created otherwise).
    """

    def __init__(self, ring: CameraRing, camera_names: Optional[Sequence[str]],
                 on_ring_frame: Callable[[RingFrame], None], slop: float = 0.03, timeout: float = 0.25,
                 use_tf: bool = True, camera_info_fallback: bool = False, ignore_ids: Collection[int] = (),
                 poll_period: float = 0.05, tf_buffer: Optional[tf2_ros.Buffer] = None):
        names = resolve_camera_names(ring, camera_names)
        self.core = RingInputCore(ring, names, slop=slop, timeout=timeout, ignore_ids=ignore_ids,
                                  camera_info_fallback=camera_info_fallback, extrinsics_from_ring=not use_tf)
        self.use_tf = use_tf
        self._on_ring_frame = on_ring_frame
        self._lock = threading.Lock()          # guards the core
        self._deliver_lock = threading.Lock()  # one on_ring_frame at a time
        self._ready: "collections.deque[RingFrame]" = collections.deque()  # filled in order under _lock
        self._info_keys: Dict[str, Tuple] = {}
        self._tf_frames: Dict[str, str] = {}   # camera -> frame_id its cached extrinsics belong to
        self._t0 = time.monotonic()
        if use_tf:
            self.tf_buffer = tf_buffer or tf2_ros.Buffer()
            self._tf_listener = None if tf_buffer else tf2_ros.TransformListener(self.tf_buffer)
        self._subs = []
        for name in names:
            ns = ring[name].namespace.strip("/")
            prefix = f"{ns}/" if ns else ""
            self._subs.append(rospy.Subscriber(f"{prefix}fiducial_vertices", FiducialArray, self._on_fiducials,
                                               callback_args=name, queue_size=5))
            self._subs.append(rospy.Subscriber(f"{prefix}camera_info", CameraInfo, self._on_camera_info,
                                               callback_args=name, queue_size=1))
        # reset=True: a bag loop moves ROS time backwards, which would otherwise kill the timer thread.
        self._timer = rospy.Timer(rospy.Duration(poll_period), self._on_timer, reset=True)
        rospy.loginfo("ring input: %d cameras (%s), slop %.3f s, timeout %.3f s, extrinsics from %s, "
                      "intrinsics from camera_info%s", len(names), ", ".join(names), slop, timeout,
                      "tf" if use_tf else "the ring file", " (ring file as fallback)" if camera_info_fallback else "")

    # --- public -----------------------------------------------------------------------------

    @property
    def ring(self) -> CameraRing:
        """The ring with the extrinsics in force (tf's once looked up)."""
        return self.core.ring

    @property
    def camera_names(self) -> List[str]:
        return list(self.core.camera_names)

    def silent_cameras(self, silence: float = 1.0) -> List[str]:
        """Cameras with no usable detections for ``silence`` s (or never): dead, or lacking calibration."""
        with self._lock:
            return self.core.silent_cameras(self._now(), silence)

    @property
    def rejected(self) -> Dict[str, Dict[str, int]]:
        """camera -> {reason: count} of dropped detections (NaN, degenerate, duplicate id, ...)."""
        return {k: dict(v) for k, v in self.core.rejected.items()}

    @property
    def skipped(self) -> Dict[str, Dict[str, int]]:
        """camera -> {reason: count} of camera frames skipped (no camera_info, no extrinsics)."""
        return {k: dict(v) for k, v in self.core.skipped.items()}

    def shutdown(self) -> None:
        """Stop the subscriptions and the timer."""
        self._timer.shutdown()
        for s in self._subs:
            s.unregister()

    # --- callbacks --------------------------------------------------------------------------

    def _now(self) -> float:
        # Wall clock, not ROS time: the timeout is about real waiting, and /clock may jump (bags).
        return time.monotonic() - self._t0

    def _on_camera_info(self, msg: CameraInfo, camera: str) -> None:
        key = (tuple(msg.K), tuple(msg.D), msg.distortion_model, msg.width, msg.height)
        if self._info_keys.get(camera) == key:
            return
        try:
            model = camera_info_to_model(msg, name=camera)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"ring input: {camera}: unusable camera_info: {exc}")
            return
        with self._lock:
            self.core.set_camera_model(camera, model)
        self._info_keys[camera] = key

    def _extrinsics_ready(self, camera: str, frame_id: str) -> bool:
        """Look T_base_cam up in tf once per (camera, frame_id); True when the core has it."""
        if not self.use_tf:
            return True
        frame_id = (frame_id or self.core.calibrated_ring[camera].frame_id).lstrip("/")
        if self._tf_frames.get(camera) == frame_id:
            return True
        base = self.core.calibrated_ring.base_frame
        try:
            msg = self.tf_buffer.lookup_transform(base, frame_id, rospy.Time(0))
            T = msg_to_transform(msg.transform, f"tf {base} -> {frame_id}")
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException) as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"ring input: {camera}: no tf {base} -> {frame_id} yet "
                                                f"({type(exc).__name__}); skipping its detections")
            return False
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"ring input: {camera}: bad tf: {exc}")
            return False
        with self._lock:
            self.core.set_extrinsics(camera, T)
        self._tf_frames[camera] = frame_id
        drift = np.linalg.norm(T[:3, 3] - self.core.calibrated_ring[camera].T_base_cam[:3, 3])
        rospy.loginfo("ring input: %s extrinsics from tf %s -> %s (%.1f mm from the ring file)", camera, base,
                      frame_id, 1000.0 * drift)
        return True

    def _on_fiducials(self, msg: FiducialArray, camera: str) -> None:
        try:
            has_tf = self._extrinsics_ready(camera, msg.header.frame_id)
            observations = fiducial_array_to_observations(msg)
            with self._lock:
                if not has_tf:
                    counts = self.core.skipped[camera]
                    counts[SKIP_NO_EXTRINSICS] = counts.get(SKIP_NO_EXTRINSICS, 0) + 1
                    self._ready.extend(self.core.poll(self._now()))
                    skipped, dropped = None, {}
                else:
                    frames, skipped, dropped = self.core.add_detections(camera, stamp_to_sec(msg.header.stamp),
                                                                        observations, self._now())
                    self._ready.extend(frames)
            if skipped:
                hint = " (set camera_info_fallback: true to use the ring file's)" if skipped == SKIP_NO_CAMERA_INFO else ""
                rospy.logwarn_throttle(WARN_PERIOD, f"ring input: {camera}: {skipped}{hint}; skipping its detections")
            if dropped:
                rospy.logwarn_throttle(WARN_PERIOD, f"ring input: {camera}: dropped malformed detections {dropped}")
            self._deliver()
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"ring input: {camera}: {exc}")

    def _on_timer(self, _event) -> None:
        with self._lock:
            self._ready.extend(self.core.poll(self._now()))
        self._deliver()

    def _deliver(self) -> None:
        # Frames were queued in stamp order under _lock; whichever thread drains delivers them in
        # that order, one at a time.
        with self._deliver_lock:
            while self._ready:
                frame = self._ready.popleft()
                try:
                    self._on_ring_frame(frame)
                except ArucoRingError as exc:
                    rospy.logwarn_throttle(WARN_PERIOD, f"ring input: ring frame at {frame.stamp:.3f} s: {exc}")
