"""``ring_tf`` node: publishes the ring's extrinsics as static transforms.

Reads the ring file (``config/ring.yaml`` format, see :mod:`aruco_ring_localization.ring`) and
publishes one static transform ``<base_frame> -> <camera frame_id>`` per camera
(``base_link -> cam0_optical_frame`` ... ``cam7_optical_frame``).

All transforms go out in ONE ``StaticTransformBroadcaster.sendTransform`` call: ``/tf_static``
is latched and a latched publisher keeps only its last message, so sending them one by one
would leave late-joining listeners with only the last camera.

Parameters: :class:`aruco_ring_localization.schemas.RingTfConfig` (``~ring_file``, default the
package's ``config/ring.yaml``; ``~map_file``: a marker map whose ``ring_calibration``, the
extrinsics refined by bundle adjustment while mapping, is published instead of the ring file's.
Localization uses the refined calibration this way; mapping must not).

Exits with code 1 and a fatal log naming the file and the key when the ring file is unusable.
"""
from __future__ import annotations

import os
import sys
from typing import List, Optional, Sequence

import rospkg
import rospy
import tf2_ros
from geometry_msgs.msg import TransformStamped

from ..errors import ConfigError
from ..marker_map import MarkerMap
from ..ring import CameraRing, apply_refined_extrinsics
from ..schemas import RingTfConfig
from .conversions import make_transform_stamped
from .params import read_config

PACKAGE = "aruco_ring_localization"


def default_ring_file() -> str:
    """The ring file shipped with the package (``config/ring.yaml``)."""
    return os.path.join(rospkg.RosPack().get_path(PACKAGE), "config", "ring.yaml")


def ring_transforms(ring: CameraRing, stamp: rospy.Time) -> List[TransformStamped]:
    """One ``TransformStamped`` per camera: parent ``ring.base_frame``, child the camera's optical frame.

    Args:
        ring: the camera ring; each camera's ``T_base_cam`` (4x4, metres) is its optical frame's
            pose in the base frame.
        stamp: header stamp of every transform.
    """
    return [make_transform_stamped(camera.T_base_cam, ring.base_frame, camera.frame_id, stamp)
            for camera in ring.cameras]


def _load_ring(path: str) -> Optional[CameraRing]:
    """The ring in ``path``, or None after a fatal log saying why it is unusable."""
    try:
        return CameraRing.load(path)
    except ConfigError as exc:
        rospy.logfatal("ring_tf: cannot use the ring file: %s", exc)
    except OSError as exc:
        rospy.logfatal("ring_tf: cannot read the ring file %s: %s", path, exc)
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the node until shutdown; returns the process exit code (1 when the ring file is bad)."""
    rospy.init_node("ring_tf", argv=list(argv) if argv is not None else None)
    try:
        config = read_config(RingTfConfig)
    except ConfigError as exc:
        rospy.logfatal("ring_tf: %s", exc)
        rospy.signal_shutdown("bad parameter")
        return 1
    ring_file = config.ring_file or default_ring_file()
    ring = _load_ring(ring_file)
    if ring is None:
        rospy.signal_shutdown("bad ring file")
        return 1
    map_file = config.map_file
    if map_file:
        try:
            marker_map = MarkerMap.load(map_file)
            if marker_map.ring_extrinsics:
                ring = apply_refined_extrinsics(ring, marker_map.ring_extrinsics, marker_map.ring_base_frame,
                                                source=map_file)
                rospy.loginfo("ring_tf: using the extrinsics of %d cameras refined while mapping (%s)",
                              len(marker_map.ring_extrinsics), map_file)
            else:
                rospy.loginfo("ring_tf: %s carries no refined ring calibration; using %s", map_file, ring_file)
        except ConfigError as exc:
            rospy.logfatal("ring_tf: cannot use the map's ring calibration: %s", exc)
            rospy.signal_shutdown("bad map file")
            return 1

    broadcaster = tf2_ros.StaticTransformBroadcaster()
    transforms = ring_transforms(ring, rospy.Time.now())
    broadcaster.sendTransform(transforms)
    rospy.loginfo("ring_tf: published %d static transforms %s -> {%s} from %s", len(transforms),
                  ring.base_frame, ", ".join(t.child_frame_id for t in transforms), ring_file)
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
