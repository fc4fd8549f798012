#!/usr/bin/env python3
"""rostest node for simulator_detector.test: rendered images through two detector nodes.

The simulator holds the robot at the scene's mapping pose; this node rebuilds the same true rig
(same seed) and checks that each detector publishes exactly the markers the simulator says are
visible, with corners close to the true projection, and that the simulator's other outputs
(ground truth, waypoint index, odometry, scan, camera_info) are there and consistent.
"""
from __future__ import annotations

import os
import threading
import unittest

import numpy as np
import rospkg
import rospy
import rostest
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, LaserScan
from std_msgs.msg import Int32

from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import fiducial_array_to_observations, pose_msg_to_transform
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

PKG = "aruco_ring_localization"
CAMERAS = ("cam1", "cam5")


class SimulatorDetectorTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("simulator_detector_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.scene = Scene.load(os.path.join(root, "config", "lab_scene.yaml"))
        cls.ring = CameraRing.load(os.path.join(root, "config", "ring.yaml"))
        seed = int(rospy.get_param("~seed", 3))
        cls.sim = RingSimulator(cls.scene, perturb_ring(cls.ring, seed=seed), seed=seed)
        cls.lock = threading.Lock()
        cls.msgs = {}
        for cam in CAMERAS:
            rospy.Subscriber(f"ring/{cam}/fiducial_vertices", FiducialArray, cls._keep, callback_args=cam)
            rospy.Subscriber(f"ring/{cam}/camera_info", CameraInfo, cls._keep, callback_args=cam + "/info")
        for topic, typ in (("sim/ground_truth", PoseStamped), ("sim/at_waypoint", Int32), ("odom", Odometry),
                           ("scan", LaserScan)):
            rospy.Subscriber(topic, typ, cls._keep, callback_args=topic)

    @classmethod
    def _keep(cls, msg, key):
        with cls.lock:
            cls.msgs.setdefault(key, []).append(msg)

    def _wait(self, keys, n=3, timeout=60.0):
        end = rospy.get_time() + timeout
        while not rospy.is_shutdown() and rospy.get_time() < end:
            with self.lock:
                if all(len(self.msgs.get(k, [])) >= n for k in keys):
                    return
            rospy.sleep(0.1)
        with self.lock:
            counts = {k: len(self.msgs.get(k, [])) for k in keys}
        self.fail(f"timed out waiting for {n} messages on each of {counts}")

    def test_detectors_find_the_visible_markers(self):
        self._wait([*CAMERAS, "sim/ground_truth"])
        T = self.scene.T_world_base(self.scene.mapping_pose)
        visible = self.sim.visible(T)
        errors = []
        for cam in CAMERAS:
            with self.lock:
                msg = self.msgs[cam][-1]
            self.assertEqual(msg.header.frame_id, self.ring[cam].frame_id)
            found = {o.marker_id: o.corners for o in fiducial_array_to_observations(msg)}
            expected = {i: c for i, c in visible[cam]}
            self.assertTrue(expected, f"{cam}: the test pose should see markers")
            self.assertEqual(set(found), set(expected), f"{cam}: detected {sorted(found)}, visible {sorted(expected)}")
            for i, c in expected.items():
                errors.extend(np.linalg.norm(found[i] - c, axis=1))
        med = float(np.median(errors))
        self.assertLess(med, 0.5, f"median corner error {med:.3f} px over {len(errors)} corners")

    def test_ground_truth_waypoint_odom_scan_camera_info(self):
        self._wait(["sim/ground_truth", "sim/at_waypoint", "odom", "scan", "cam1/info"])
        with self.lock:
            gt = self.msgs["sim/ground_truth"][-1]
            wp = self.msgs["sim/at_waypoint"][-1]
            odom = self.msgs["odom"][-1]
            scan = self.msgs["scan"][-1]
            info = self.msgs["cam1/info"][-1]
        T = pose_msg_to_transform(gt.pose)
        x, y, yaw = self.scene.mapping_pose
        self.assertEqual(gt.header.frame_id, "world")
        self.assertLess(np.hypot(T[0, 3] - x, T[1, 3] - y), 1e-6)
        self.assertEqual(wp.data, 0, "holding waypoint 0 (the mapping pose)")
        self.assertEqual((odom.header.frame_id, odom.child_frame_id), ("odom", "base_link"))
        r = np.array(scan.ranges)
        self.assertEqual(r.size, 360)
        self.assertTrue(np.all(np.isfinite(r)) and r.max() < 8.0, f"scan ranges {r.min():.2f}..{r.max():.2f} m")
        self.assertEqual(info.header.frame_id, self.ring["cam1"].frame_id)
        self.assertTrue(np.allclose(np.reshape(info.K, (3, 3)), self.ring["cam1"].model.K))


if __name__ == "__main__":
    rostest.rosrun(PKG, "simulator_detector", SimulatorDetectorTest)
