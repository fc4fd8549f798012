#!/usr/bin/env python3
"""Rostest (calibrate_ring.test): record the simulator node's route of turns and drives into a bag,
calibrate the ring from rough values with ``aruco_ring calibrate-ring``, compare with the true rig.

The bag is written by this node from what it receives through the master (each camera's
fiducial_vertices and camera_info, odom), as ``rosbag record`` would. The true rig is the
simulator's (the ring file perturbed with the node's seed, :class:`SimulatorCore`).
"""
from __future__ import annotations

import os
import subprocess
import tempfile
import threading
import unittest

import fiducial_msgs.msg as fiducial_msgs
import numpy as np
import rosbag
import rospkg
import rospy
import rostest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import load_config
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.calibration_run import rough_ring
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.simulation.simulator import SimulatorCore
from sim_route import HeldWaypoints

PKG = "aruco_ring_localization"


class CalibrateRingSimTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("calibrate_ring_rostest")
        root = rospkg.RosPack().get_path(PKG)
        config = load_config(SimulatorConfig, rospy.get_param("/simulator"), source="/simulator")
        ring = CameraRing.load(f"{root}/config/ring.yaml")
        cls.core = SimulatorCore(config, Scene.default(), ring)
        cls.true = cls.core.true_ring
        cls.tmp = tempfile.mkdtemp(prefix="calibrate_ring_rostest_")
        cls.rough_path = os.path.join(cls.tmp, "rough.yaml")
        rough_ring(cls.true, seed=7).save(cls.rough_path)
        cls.bag_path = os.path.join(cls.tmp, "calib.bag")
        cls.lock = threading.Lock()
        cls.bag = rosbag.Bag(cls.bag_path, "w")
        cls.closed = False
        cls.counts = {"det": 0, "odom": 0}
        subs = [rospy.Subscriber("/odom", Odometry, cls._writer("/odom", "odom"), queue_size=200)]
        for cam in ring.cameras:
            ns = "/" + cam.namespace.strip("/")
            subs.append(rospy.Subscriber(f"{ns}/fiducial_vertices", fiducial_msgs.FiducialArray,
                                         cls._writer(f"{ns}/fiducial_vertices", "det"), queue_size=200))
            subs.append(rospy.Subscriber(f"{ns}/camera_info", CameraInfo, cls._writer(f"{ns}/camera_info", None),
                                         queue_size=50))
        route = HeldWaypoints()
        try:
            # Generous: the route is ~60 simulated s; a loaded machine runs the simulator slower.
            route.wait_for_waypoint(len(cls.core.waypoints()) - 1, timeout=300.0)
        finally:
            for s in subs:
                s.unregister()
            with cls.lock:
                cls.closed = True
                cls.bag.close()
        cls.out = os.path.join(cls.tmp, "ring.yaml")
        cls.proc = subprocess.run(["aruco_ring", "calibrate-ring", cls.bag_path, "--ring", cls.rough_path,
                                   "--out", cls.out], capture_output=True, text=True, timeout=600)

    @classmethod
    def _writer(cls, topic, kind):
        def cb(msg):
            with cls.lock:
                if cls.closed:
                    return
                cls.bag.write(topic, msg, rospy.Time.now())
                if kind:
                    cls.counts[kind] += 1
        return cb

    def test_1_recorded(self):
        self.assertGreater(self.counts["det"], 8 * 100, self.counts)
        self.assertGreater(self.counts["odom"], 100, self.counts)

    def test_2_calibrated_from_rough_values(self):
        self.assertEqual(self.proc.returncode, 0, self.proc.stdout + self.proc.stderr)
        est = CameraRing.load(self.out)
        rough = CameraRing.load(self.rough_path)
        G = geo.average_transforms([c.T_base_cam @ geo.inverse(est[c.name].T_base_cam) for c in self.true])
        for c in self.true:
            before = geo.pose_distance(c.T_base_cam, rough[c.name].T_base_cam)
            self.assertGreater(before[0], 0.005, c.name)
            rel = geo.inverse(c.T_base_cam) @ G @ est[c.name].T_base_cam
            mm, deg = 1000 * np.linalg.norm(rel[:3, 3]), np.degrees(geo.rotation_angle(rel[:3, :3]))
            self.assertLess(mm, 1.0, f"{c.name}: {mm:.2f} mm relative to the ring\n{self.proc.stdout}")
            self.assertLess(deg, 0.05, f"{c.name}: {deg:.3f} deg relative to the ring\n{self.proc.stdout}")
            direct = geo.inverse(c.T_base_cam) @ est[c.name].T_base_cam
            # In base_link: the heading from the odometry; only the height is unobservable (warned).
            self.assertLess(np.degrees(geo.rotation_angle(direct[:3, :3])), 0.2, f"{c.name}\n{self.proc.stdout}")
            self.assertLess(1000 * np.linalg.norm(direct[:2, 3]), 2.0, f"{c.name}\n{self.proc.stdout}")
        self.assertIn("warning: planar motion only", self.proc.stdout)
        self.assertNotIn("no odometry", self.proc.stdout)


if __name__ == "__main__":
    rostest.rosrun(PKG, "calibrate_ring_sim", CalibrateRingSimTest)
