#!/usr/bin/env python3
"""Publishes every topic and frame the rviz configurations show, from the simulated lab (for the rviz test).

Not a test itself: ``test_rviz_configs.py`` runs it against its own roscore. It publishes, with
the robot standing at the plate centre of the default scene (marker map = the scene's truth, so
``map`` is the scene's world frame):

- tf: ``map -> base_link`` (our pose), ``map -> sim_ground_truth`` (the truth, 1 cm away),
  ``base_link -> laser``, static ``base_link -> camK_optical_frame`` (the ring) and
  ``map -> marker_<id>``;
- ``/mapper/markers`` and ``/localizer/markers`` (MarkerArray of the map), ``/localizer/pose``
  (PoseWithCovarianceStamped), ``/localizer/camera_estimates`` (PoseArray), ``/localizer/odometry``,
  ``/scan`` (LaserScan of the room walls), ``/map`` (an OccupancyGrid of the room, gmapping's
  place), ``/comparison/text`` and ``/ring_tf/markers`` (the ring's fields of view and the robot,
  as ring_tf publishes them).

Runs until killed.
"""
from __future__ import annotations

import numpy as np
import rospy
import tf2_ros
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from sensor_msgs.msg import LaserScan
from visualization_msgs.msg import Marker, MarkerArray

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import make_transform_stamped, pose_to_msg, se2_covariance_to_pose_covariance
from aruco_ring_localization.ros.mapper import map_to_marker_array
from aruco_ring_localization.ros.ring_tf import default_ring_file, ring_markers, ring_transforms
from aruco_ring_localization.simulation.scene import Scene


def wall_ranges(scene: Scene, x: float, y: float, yaw: float, angles: np.ndarray, max_range: float) -> np.ndarray:
    """Ranges (m) from (x, y) along ``yaw + angles`` to the nearest room wall or post outline."""
    segs = np.concatenate([scene.room.wall_segments()] + [p.segments() for p in scene.posts])
    out = np.full(len(angles), np.inf)
    for k, a in enumerate(angles):
        d = np.array([np.cos(yaw + a), np.sin(yaw + a)])
        for (p, q) in segs:
            e = q - p
            den = d[0] * (-e[1]) + d[1] * e[0]
            if abs(den) < 1e-12:
                continue
            w = p - (x, y)
            t = (w[0] * (-e[1]) + w[1] * e[0]) / den
            s = (d[0] * w[1] - d[1] * w[0]) / den
            if t > 0 and 0 <= s <= 1:
                out[k] = min(out[k], t)
    return np.where(out <= max_range, out, np.inf)


def room_grid(scene: Scene, resolution: float = 0.05) -> OccupancyGrid:
    """Occupancy grid of the room: free inside, occupied walls and posts."""
    x0, y0 = scene.room.origin
    w, h = int(scene.room.size[0] / resolution) + 2, int(scene.room.size[1] / resolution) + 2
    grid = np.zeros((h, w), dtype=np.int8)
    grid[[0, 1, -2, -1], :] = 100
    grid[:, [0, 1, -2, -1]] = 100
    for post in scene.posts:
        cx, cy = post.centre
        i0, i1 = int((cy - post.side / 2 - y0) / resolution), int((cy + post.side / 2 - y0) / resolution)
        j0, j1 = int((cx - post.side / 2 - x0) / resolution), int((cx + post.side / 2 - x0) / resolution)
        grid[max(i0, 0):i1 + 1, max(j0, 0):j1 + 1] = 100
    msg = OccupancyGrid()
    msg.header.frame_id = "map"
    msg.info.resolution = resolution
    msg.info.width, msg.info.height = w, h
    msg.info.origin.position.x, msg.info.origin.position.y = x0 - resolution, y0 - resolution
    msg.info.origin.orientation.w = 1.0
    msg.data = grid.ravel().tolist()
    return msg


def main() -> None:
    rospy.init_node("rviz_scene_publisher")
    scene = Scene.default()
    ring = CameraRing.load(default_ring_file())
    truth = scene.truth_map(frame_id="map")
    x, y, yaw = scene.mapping_pose[0], scene.mapping_pose[1], scene.mapping_pose[2] + 0.3
    T_map_base = geo.transform_from_se2(x, y, yaw)

    static = tf2_ros.StaticTransformBroadcaster()
    now = rospy.Time.now()
    statics = ring_transforms(ring, now)
    statics.append(make_transform_stamped(geo.transform_from_se2(0.2, 0.0, 0.0, 0.3), ring.base_frame, "laser", now))
    statics += [make_transform_stamped(e.T_map_marker, "map", f"marker_{e.marker_id}", now) for e in truth]
    static.sendTransform(statics)
    tfb = tf2_ros.TransformBroadcaster()

    latched = dict(queue_size=1, latch=True)
    pubs = {
        "mapper": rospy.Publisher("/mapper/markers", type(map_to_marker_array(truth, now)), **latched),
        "loc_markers": rospy.Publisher("/localizer/markers", type(map_to_marker_array(truth, now)), **latched),
        "grid": rospy.Publisher("/map", OccupancyGrid, **latched),
        "pose": rospy.Publisher("/localizer/pose", PoseWithCovarianceStamped, queue_size=5),
        "cams": rospy.Publisher("/localizer/camera_estimates", PoseArray, queue_size=5),
        "odom": rospy.Publisher("/localizer/odometry", Odometry, queue_size=5),
        "scan": rospy.Publisher("/scan", LaserScan, queue_size=5),
        "text": rospy.Publisher("/comparison/text", Marker, queue_size=5),
    }
    pubs["ring"] = rospy.Publisher("/ring_tf/markers", MarkerArray, **latched)
    pubs["ring"].publish(ring_markers(ring, rospy.Time(0), 1.0))
    pubs["mapper"].publish(map_to_marker_array(truth, now))
    pubs["loc_markers"].publish(map_to_marker_array(truth, now))
    pubs["grid"].publish(room_grid(scene))
    rng = np.random.default_rng(0)
    cam_poses = [geo.transform_from_se2(x + d[0], y + d[1], yaw + d[2])
                 for d in rng.normal(scale=[0.03, 0.03, 0.02], size=(len(ring.cameras), 3))]
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    ranges = wall_ranges(scene, x + 0.2 * np.cos(yaw), y + 0.2 * np.sin(yaw), yaw, angles, 12.0)
    rate = rospy.Rate(10)
    ring_msg = ring_markers(ring, rospy.Time(0), 1.0)
    tick = 0
    while not rospy.is_shutdown():
        stamp = rospy.Time.now()
        if tick % 10 == 0:  # as ring_tf does: again each second
            pubs["ring"].publish(ring_msg)
        tick += 1
        tfb.sendTransform([make_transform_stamped(T_map_base, "map", ring.base_frame, stamp),
                           make_transform_stamped(geo.transform_from_se2(x + 0.01, y, yaw), "map",
                                                  "sim_ground_truth", stamp)])
        pose = PoseWithCovarianceStamped()
        pose.header.stamp, pose.header.frame_id = stamp, "map"
        pose.pose.pose = pose_to_msg(T_map_base)
        pose.pose.covariance = se2_covariance_to_pose_covariance(np.diag([0.05 ** 2, 0.03 ** 2, 0.05 ** 2]))
        pubs["pose"].publish(pose)
        odom = Odometry()
        odom.header = pose.header
        odom.child_frame_id = ring.base_frame
        odom.pose = pose.pose
        pubs["odom"].publish(odom)
        cams = PoseArray()
        cams.header = pose.header
        cams.poses = [pose_to_msg(T) for T in cam_poses]
        pubs["cams"].publish(cams)
        scan = LaserScan()
        scan.header.stamp, scan.header.frame_id = stamp, "laser"
        scan.angle_min, scan.angle_max = float(angles[0]), float(angles[-1])
        scan.angle_increment = float(angles[1] - angles[0])
        scan.range_min, scan.range_max = 0.1, 12.0
        scan.ranges = [float(r) for r in ranges]
        pubs["scan"].publish(scan)
        text = Marker()
        text.header.frame_id = "map"
        text.ns, text.id, text.type, text.action = "comparison", 0, Marker.TEXT_VIEW_FACING, Marker.ADD
        text.pose.position.x, text.pose.position.y, text.pose.position.z = x, y, 1.5
        text.pose.orientation.w = 1.0
        text.scale.z = 0.25
        text.color.r = text.color.g = text.color.b = text.color.a = 1.0
        text.text = "error 1.0 cm (x +1.0, y +0.0), yaw +0.00 deg"
        pubs["text"].publish(text)
        rate.sleep()


if __name__ == "__main__":
    main()
