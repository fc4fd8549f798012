"""``mapper`` node: builds the marker map from the ring's detections.

Subscribes (through :class:`ros.ring_input.RingInput`): ``<ns>/fiducial_vertices`` and
``<ns>/camera_info`` of every ring camera; extrinsics from tf (or the ring file).

Publishes:
    ``~markers`` (visualization_msgs/MarkerArray, latched): a thin box per mapped marker, coloured
        by its position uncertainty (green <= 2 mm, yellow ~1 cm, red >= 5 cm), and its id as text.
    ``fiducial_map`` (fiducial_msgs/FiducialMapEntryArray, latched): as fiducial_slam publishes it.
    static tf ``<map_frame> -> marker_<id>`` for every marker, all in ONE sendTransform call
        (/tf_static is latched and keeps only a publisher's last message).

Services:
    ``~save_map`` (std_srvs/Trigger): builds the map with ``method`` (``refined``: bundle
        adjustment), writes ``map_file`` atomically (previous file kept as ``.bak``), answers with
        the path and a summary.
    ``~clear`` (std_srvs/Trigger): forgets every observation.

Progress (markers mapped, observations per marker, markers seen but not linked, silent cameras)
goes to the log every ``progress_period`` seconds. With ``save_on_shutdown`` the map is saved
when the node stops. Parameters: :class:`MapperParams` (documented in config/mapping.yaml).
"""
from __future__ import annotations

import os
import sys
import threading
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import rospy
import tf2_ros
from fiducial_msgs.msg import FiducialMapEntry, FiducialMapEntryArray
from std_srvs.srv import Trigger, TriggerResponse
from visualization_msgs.msg import Marker, MarkerArray

from .. import geometry as geo
from ..bundle_adjustment import BAOptions
from ..errors import ArucoRingError, ConfigError
from ..detections import RingFrame
from ..mapping import MapBuilder, MappingOptions
from ..marker_map import MarkerMap
from ..markers import MarkerSizes, parse_id_list
from ..ring import CameraRing
from .conversions import make_transform_stamped, pose_to_msg
from .params import read_params
from .ring_input import RingInput
from .ring_tf import default_ring_file

WARN_PERIOD = 5.0


@dataclass(frozen=True)
class MapperParams:
    """Private parameters (prose in config/mapping.yaml)."""

    ring_file: str = ""
    cameras: tuple = ()
    map_file: str = ""
    method: str = "refined"
    reference_marker: int = -1
    map_frame: str = "map"
    fiducial_len: float = 0.2
    fiducial_len_override: str = ""
    ignore_fiducials: str = ""
    slop: float = 0.03
    timeout: float = 0.25
    extrinsics: str = "tf"
    camera_info_fallback: str = "none"
    save_on_shutdown: bool = False
    publish_period: float = 1.0
    progress_period: float = 5.0
    max_ambiguity: float = 0.6
    max_reprojection_px: float = 3.0
    max_distance: float = 12.0
    still_px: float = 1.5
    max_frames_per_station: int = 30
    refine_extrinsics: bool = True
    pixel_sigma: float = 0.5


def uncertainty_colour(std_m: float):
    """(r, g, b) from green (<= 2 mm) through yellow to red (>= 5 cm), log scale."""
    a = float(np.clip((np.log10(max(std_m, 1e-6)) - np.log10(0.002)) / (np.log10(0.05) - np.log10(0.002)), 0, 1))
    return (min(1.0, 2 * a), min(1.0, 2 * (1 - a)), 0.0)


def map_to_marker_array(m: MarkerMap, stamp: rospy.Time, ns: str = "aruco_map") -> MarkerArray:
    """A thin box per marker (its side x side x 5 mm, coloured by uncertainty) and its id as text."""
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    out.markers.append(clear)
    for e in m:
        box = Marker()
        box.header.frame_id = m.frame_id
        box.header.stamp = stamp
        box.ns = ns
        box.id = 2 * e.marker_id
        box.type = Marker.CUBE
        box.action = Marker.ADD
        box.pose = pose_to_msg(e.T_map_marker)
        box.scale.x = box.scale.y = float(e.size)
        box.scale.z = 0.005
        r, g, b = uncertainty_colour(float(np.max(e.position_std)) if e.marker_id != m.reference_marker else 0.0)
        box.color.r, box.color.g, box.color.b, box.color.a = r, g, b, 0.9
        text = Marker()
        text.header = box.header
        text.ns = ns + "_ids"
        text.id = 2 * e.marker_id + 1
        text.type = Marker.TEXT_VIEW_FACING
        text.action = Marker.ADD
        text.pose = pose_to_msg(geo.make_transform(t=e.T_map_marker[:3, 3] + [0.0, 0.0, 0.6 * e.size]))
        text.scale.z = max(0.08, 0.5 * float(e.size))
        text.color.r = text.color.g = text.color.b = text.color.a = 1.0
        text.text = str(e.marker_id) + (" (ref)" if e.marker_id == m.reference_marker else "")
        out.markers.extend([box, text])
    return out


def map_to_fiducial_map(m: MarkerMap) -> FiducialMapEntryArray:
    """fiducial_slam's map message: position (m) and fixed-axis roll, pitch, yaw (rad)."""
    out = FiducialMapEntryArray()
    for e in m:
        r, p, y = geo.rpy_from_matrix(e.T_map_marker)
        t = e.T_map_marker[:3, 3]
        out.fiducials.append(FiducialMapEntry(fiducial_id=int(e.marker_id), x=float(t[0]), y=float(t[1]),
                                              z=float(t[2]), rx=float(r), ry=float(p), rz=float(y)))
    return out


def default_map_file() -> str:
    return os.path.join(os.environ.get("ROS_HOME", os.path.expanduser("~/.ros")), "aruco_map.yaml")


class MapperNode:
    """The node's state; ROS I/O only, the mapping itself is :class:`MapBuilder`."""

    def __init__(self, params: MapperParams, ring: CameraRing):
        self.params = params
        if params.method not in ("paper", "refined"):
            raise ConfigError(f"expected 'paper' or 'refined', got {params.method!r}", key="~method")
        if params.extrinsics not in ("tf", "ring_file"):
            raise ConfigError(f"expected 'tf' or 'ring_file', got {params.extrinsics!r}", key="~extrinsics")
        if params.camera_info_fallback not in ("none", "ring"):
            raise ConfigError(f"expected 'none' or 'ring', got {params.camera_info_fallback!r}",
                              key="~camera_info_fallback")
        self.map_file = os.path.expanduser(params.map_file) or default_map_file()
        options = MappingOptions(max_ambiguity=params.max_ambiguity, max_reprojection_px=params.max_reprojection_px,
                                 max_distance=params.max_distance, still_px=params.still_px,
                                 max_frames_per_station=params.max_frames_per_station,
                                 ba=BAOptions(refine_extrinsics=params.refine_extrinsics,
                                              pixel_sigma=params.pixel_sigma))
        ignore = parse_id_list(params.ignore_fiducials, key="~ignore_fiducials")
        self.builder = MapBuilder(ring, MarkerSizes.parse(params.fiducial_len, params.fiducial_len_override),
                                  method=params.method,
                                  reference_marker=params.reference_marker if params.reference_marker >= 0 else None,
                                  options=options, frame_id=params.map_frame, ignore_ids=ignore)
        self._lock = threading.Lock()
        self._published_version = -1
        self._map: Optional[MarkerMap] = None
        self.pub_markers = rospy.Publisher("~markers", MarkerArray, queue_size=1, latch=True)
        self.pub_fiducial_map = rospy.Publisher("fiducial_map", FiducialMapEntryArray, queue_size=1, latch=True)
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        self.ring_input = RingInput(ring, list(params.cameras) or None, self.on_ring_frame, slop=params.slop,
                                    timeout=params.timeout, use_tf=params.extrinsics == "tf",
                                    camera_info_fallback=params.camera_info_fallback == "ring", ignore_ids=ignore)
        rospy.Service("~save_map", Trigger, self.on_save_map)
        rospy.Service("~clear", Trigger, self.on_clear)
        rospy.Timer(rospy.Duration(params.publish_period), self.on_publish_timer, reset=True)
        rospy.Timer(rospy.Duration(params.progress_period), self.on_progress_timer, reset=True)
        rospy.on_shutdown(self.on_shutdown)
        rospy.loginfo("mapper: method %s, map file %s, map frame %s", params.method, self.map_file, params.map_frame)

    # --- input ------------------------------------------------------------------------------

    def on_ring_frame(self, frame: RingFrame) -> None:
        with self._lock:
            self.builder.ring = self.ring_input.ring
            self.builder.add_frame(frame)

    # --- output -----------------------------------------------------------------------------

    def publish(self, m: MarkerMap) -> None:
        stamp = rospy.Time.now()
        self.pub_markers.publish(map_to_marker_array(m, stamp))
        self.pub_fiducial_map.publish(map_to_fiducial_map(m))
        transforms = [make_transform_stamped(e.T_map_marker, m.frame_id, f"marker_{e.marker_id}", stamp) for e in m]
        if transforms:
            self.static_tf.sendTransform(transforms)

    def on_publish_timer(self, _event) -> None:
        with self._lock:
            version = self.builder.version
            if version == self._published_version:
                return
            try:
                m = self.builder.build("paper")  # cheap live preview; ~save_map refines
            except ArucoRingError as exc:
                rospy.logwarn_throttle(WARN_PERIOD, f"mapper: no map yet: {exc}")
                return
            self._published_version = version
        self.publish(m)

    def on_progress_timer(self, _event) -> None:
        with self._lock:
            if not self.builder.frames:
                text = "mapper: no ring frame yet"
            else:
                text = "mapper: " + self.builder.format_summary()
        silent = self.ring_input.silent_cameras(2.0)
        if silent:
            text += f"; silent cameras: {silent}"
        rospy.loginfo(text)

    def save(self) -> str:
        """Build with the configured method, write atomically; returns a summary line."""
        with self._lock:
            m = self.builder.save_map(self.map_file)
            summary = self.builder.format_summary()
            ba = self.builder.last_ba if self.params.method == "refined" else None
            self._published_version = self.builder.version
        self.publish(m)
        extra = (f"; bundle adjustment RMS {ba.rms_px_before:.2f} -> {ba.rms_px_after:.2f} px in {ba.seconds:.1f} s"
                 if ba is not None else "")
        return (f"saved {len(m)} markers ({self.params.method}, map frame fixed to marker {m.reference_marker}) "
                f"to {self.map_file}: {summary}{extra}")

    def on_save_map(self, _req) -> TriggerResponse:
        try:
            text = self.save()
        except (ArucoRingError, OSError) as exc:
            rospy.logerr(f"mapper: save_map failed: {exc}")
            return TriggerResponse(success=False, message=str(exc))
        rospy.loginfo(text)
        return TriggerResponse(success=True, message=text)

    def on_clear(self, _req) -> TriggerResponse:
        with self._lock:
            self.builder.clear()
            self._published_version = -1
        self.pub_markers.publish(map_to_marker_array(MarkerMap(frame_id=self.params.map_frame), rospy.Time.now()))
        self.pub_fiducial_map.publish(FiducialMapEntryArray())
        rospy.loginfo("mapper: cleared")
        return TriggerResponse(success=True, message="cleared")

    def on_shutdown(self) -> None:
        if not self.params.save_on_shutdown:
            return
        try:
            rospy.loginfo(self.save())
        except (ArucoRingError, OSError) as exc:
            rospy.logerr(f"mapper: save on shutdown failed: {exc}")


def main(argv: Optional[Sequence[str]] = None) -> int:
    rospy.init_node("mapper", argv=list(argv) if argv is not None else None)
    try:
        params = read_params(MapperParams)
        ring_file = params.ring_file or default_ring_file()
        ring = CameraRing.load(ring_file)
        MapperNode(params, ring)
    except (ConfigError, ValueError, OSError) as exc:
        rospy.logfatal(f"mapper: {exc}")
        return 1
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
