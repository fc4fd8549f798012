#!/usr/bin/env python3
"""rostest node for comparison.test: plays the simulated ring and a fake gmapping, checks the comparison.

Owns /clock (use_sim_time). For each frame (10 per simulated second) it publishes every camera's
``camera_info`` and ``fiducial_vertices`` from :class:`RingSimulator` (true rig with the seeded
2 mm / 0.2 deg calibration error) and the reference tf ``map -> base_link`` = the ground truth
expressed in a "gmapping" map frame offset from the world (where our marker map lives) by
``T_GMAP_WORLD``. The robot stops at three poses (3 s each) with moves in between.
Named ``*_rostest.py`` so pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import os
import threading
import unittest

import numpy as np
import rospkg
import rospy
import rostest
import tf2_ros
from fiducial_msgs.msg import FiducialArray
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.evaluation.trajectories import apply_se2
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import (make_transform_stamped, model_to_camera_info, msg_to_transform,
                                                     observations_to_fiducials)
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

PKG = "aruco_ring_localization"
T_GMAP_WORLD = np.array([-4.0, -3.5, np.radians(25.0)])  # the fake gmapping map frame, (x, y, yaw) of world in it
STOPS = [(4.8, 4.2, 0.0), (5.6, 4.9, 0.8), (6.0, 4.1, -1.2)]


def path(t: float) -> np.ndarray:
    """Stop-and-go through STOPS: 3 s still, 2 s moving, ... (world frame)."""
    hold, move = 3.0, 2.0
    k = int(t // (hold + move))
    a = t - k * (hold + move)
    k = min(k, len(STOPS) - 1)
    cur = np.asarray(STOPS[k], dtype=float)
    if a <= hold or k == len(STOPS) - 1:
        return cur
    nxt = np.asarray(STOPS[k + 1], dtype=float)
    f = (a - hold) / move
    return np.array([cur[0] + f * (nxt[0] - cur[0]), cur[1] + f * (nxt[1] - cur[1]),
                     geo.wrap_angle(cur[2] + f * geo.angle_diff(nxt[2], cur[2]))])


class ComparisonSimTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("comparison_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.scene = Scene.default()
        cls.ring = CameraRing.load(f"{root}/config/ring.yaml")
        cls.sim = RingSimulator(cls.scene, perturb_ring(cls.ring, seed=0), pixel_noise=0.3, seed=1)
        cls.clock_pub = rospy.Publisher("/clock", Clock, queue_size=10)
        cls.tf_pub = tf2_ros.TransformBroadcaster()
        cls.pubs = {}
        for cam in cls.ring.cameras:
            cls.pubs[cam.name] = (rospy.Publisher(f"{cam.namespace}/fiducial_vertices", FiducialArray, queue_size=10),
                                  rospy.Publisher(f"{cam.namespace}/camera_info",
                                                  type(model_to_camera_info(cam.model)), queue_size=2, latch=True))
        cls.lock = threading.Lock()
        cls.errors = []
        cls.texts = []
        rospy.Subscriber("/comparison/errors", Float64MultiArray, cls._on_errors, queue_size=100)
        rospy.Subscriber("/comparison/text", Marker, cls._on_text, queue_size=10)
        cls.buffer = tf2_ros.Buffer()
        cls.listener = tf2_ros.TransformListener(cls.buffer)
        for _ in range(50):
            if all(p[0].get_num_connections() > 0 for p in cls.pubs.values()):
                break
            rospy.rostime.wallsleep(0.1)
        cls._play(100.0, 100.0 + 5.0 * len(STOPS) - 1.0)

    @classmethod
    def _on_errors(cls, msg):
        with cls.lock:
            cls.errors.append(list(msg.data))

    @classmethod
    def _on_text(cls, msg):
        with cls.lock:
            cls.texts.append(msg.text)

    @classmethod
    def _play(cls, t0: float, t1: float, rate_hz: float = 10.0):
        n = int(round((t1 - t0) * rate_hz))
        for k in range(n + 10):
            t = t0 + k / rate_hz
            stamp = rospy.Time.from_sec(t)
            cls.clock_pub.publish(Clock(clock=stamp))
            if k >= n:  # let the last frames through
                rospy.rostime.wallsleep(0.1)
                continue
            pose = path(t - t0)
            gm = apply_se2(T_GMAP_WORLD, pose[None])[0]
            cls.tf_pub.sendTransform(make_transform_stamped(geo.transform_from_se2(*gm), "map", "base_link", stamp))
            frame = cls.sim.observe(cls.scene.T_world_base(pose), t)
            for name, (fv, ci) in cls.pubs.items():
                info = model_to_camera_info(cls.ring[name].model, cls.ring[name].frame_id)
                info.header.stamp = stamp
                ci.publish(info)
                msg = FiducialArray()
                msg.header.stamp = stamp
                msg.header.frame_id = cls.ring[name].frame_id
                msg.fiducials = observations_to_fiducials(frame.cameras[name].observations)
                fv.publish(msg)
            rospy.rostime.wallsleep(1.0 / rate_hz)

    def test_1_live_errors_are_small(self):
        with self.lock:
            errors = np.array(self.errors)
        self.assertGreater(len(errors), 50, f"only {len(errors)} ~errors messages in 14 s of 10 Hz poses")
        late = errors[len(errors) // 2:]
        self.assertLess(np.median(late[:, 2]), 0.02, f"median live error {100 * np.median(late[:, 2]):.2f} cm")
        self.assertLess(np.max(np.abs(late[:, 3])), np.radians(1.5),
                        f"max live yaw error {np.degrees(np.max(np.abs(late[:, 3]))):.2f} deg")
        with self.lock:
            texts = list(self.texts)
        self.assertTrue(texts and "error" in texts[-1], f"rviz text: {texts[-1:] or 'none'}")

    def test_2_alignment_published_on_tf(self):
        tf = self.buffer.lookup_transform("map", "aruco_map", rospy.Time(0), rospy.Duration(5.0))
        got = geo.se2_from_transform(msg_to_transform(tf.transform))
        d = np.abs(got - T_GMAP_WORLD)
        self.assertLess(max(d[0], d[1]), 0.02, f"map -> aruco_map {got} vs {T_GMAP_WORLD}")
        self.assertLess(d[2], np.radians(0.5), f"map -> aruco_map yaw off by {np.degrees(d[2]):.3f} deg")

    def test_3_stops_and_tables(self):
        rec = rospy.ServiceProxy("/comparison/record_stop", Trigger)
        rec.wait_for_service(10.0)
        res = rec()
        self.assertTrue(res.success, res.message)
        write = rospy.ServiceProxy("/comparison/write_tables", Trigger)
        res = write()
        self.assertTrue(res.success, res.message)
        paths = res.message.split()
        table1 = next(p for p in paths if p.endswith("table1.md"))
        with open(table1) as handle:
            text = handle.read()
        rows = [line for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]
        # three automatic stops (still 3 s >= still_time 2 s) + one requested
        self.assertEqual(len(rows), 4, f"expected 4 stops in {table1}:\n{text}")
        for line in rows:
            euclid = float(line.split("|")[4])
            self.assertLess(euclid, 2.0, f"stop error {euclid} cm in row {line}")
        self.assertTrue(os.path.isfile(table1.replace("table1.md", "table2.csv")))


if __name__ == "__main__":
    rostest.rosrun(PKG, "comparison_sim", ComparisonSimTest)
