#!/usr/bin/env python3
"""rostest node for mapper_calibrate.test: the mapper (stock mapping.launch, extrinsics:=rough)
calibrates the ring from rough values while mapping.

The simulator node turns the robot on the spot and drives it between three places of the lab
(corners mode, simulated time, odometry on tf); once it has held the last waypoint, ``~save_map``
is called. Checked: the ring file written beside the map against the simulator's true rig (each
camera relative to the others, and in base_link: the heading from the odometry; the height is not
observable from a ground robot and is warned about), the ring's static tf (the calibrated values,
published by the mapper), and the map built with them. Named ``*_rostest.py`` so pytest does not
collect it (it needs rostest's master).
"""
from __future__ import annotations

import os
import shutil
import unittest

import numpy as np
import rospkg
import rospy
import rostest
import tf2_ros
from std_srvs.srv import Trigger

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import load_config
from aruco_ring_localization.evaluation.maps import format_map_error, map_error
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.calibration_run import rough_ring
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.simulation.simulator import SimulatorCore
from sim_route import HeldWaypoints

PKG = "aruco_ring_localization"
# The lab targets of issue 13 (calib_err_mm_max / _deg_max), relative to the ring.
TOL_REL_MM = 1.0
TOL_REL_DEG = 0.05
# In base_link: the heading from the odometry, the origin (x, y) from the turns (the CLI's rostest).
TOL_BASE_DEG = 0.2
TOL_BASE_XY_MM = 2.0
TOL_FIT_MAX_MM = 10.0       # the map's geometry, best fit (mapper.test: measured ~1-2 mm)
TOL_TF = 1e-6


class MapperCalibrateTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("mapper_calibrate_rostest")
        cls.root = rospkg.RosPack().get_path(PKG)
        cls.map_file = rospy.get_param("/mapper/map_file")
        cls.rough_file = rospy.get_param("/mapper/ring_file")
        cls.ring_file = os.path.splitext(cls.map_file)[0] + "_ring.yaml"
        shutil.rmtree(os.path.dirname(cls.map_file), ignore_errors=True)
        config = load_config(SimulatorConfig, rospy.get_param("/simulator"), source="/simulator")
        cls.scene = Scene.load(config.scene.file) if config.scene.file else Scene.default()
        cls.core = SimulatorCore(config, cls.scene, CameraRing.load(f"{cls.root}/config/ring.yaml"))
        cls.true = cls.core.true_ring
        cls.tf_buffer = tf2_ros.Buffer()
        cls.tf_listener = tf2_ros.TransformListener(cls.tf_buffer)
        # The route is ~60 simulated s at twice the wall clock; a loaded machine runs it slower.
        HeldWaypoints().wait_for_waypoint(len(cls.core.waypoints()) - 1, timeout=300.0)
        rospy.rostime.wallsleep(2.0)     # the odometry lookups run each second
        rospy.wait_for_service("/mapper/save_map", timeout=30.0)
        cls.response = rospy.ServiceProxy("/mapper/save_map", Trigger)()

    def test_0_the_rough_ring_is_the_generators(self):
        """ring_rough.yaml is config/ring.yaml made rough (its header says how): regenerate it if not."""
        fixture = CameraRing.load(self.rough_file)
        again = rough_ring(CameraRing.load(f"{self.root}/config/ring.yaml"), seed=7)
        for c in again:
            dt, dr = geo.pose_distance(c.T_base_cam, fixture[c.name].T_base_cam)
            self.assertLess(dt, 1e-6, f"{c.name}: regenerate {self.rough_file}")
            self.assertLess(dr, 1e-6, f"{c.name}: regenerate {self.rough_file}")

    def test_1_ring_calibrated_beside_the_map(self):
        self.assertTrue(self.response.success, f"save_map failed: {self.response.message}")
        self.assertIn("ring calibrated from rough values", self.response.message)
        self.assertIn("with odometry", self.response.message)
        self.assertIn("planar motion only", self.response.message)    # the height: warned
        est = CameraRing.load(self.ring_file)
        rough = CameraRing.load(self.rough_file)
        G = geo.average_transforms([c.T_base_cam @ geo.inverse(est[c.name].T_base_cam) for c in self.true])
        for c in self.true:
            before = geo.pose_distance(c.T_base_cam, rough[c.name].T_base_cam)
            self.assertGreater(before[0], 0.005, c.name)
            rel = geo.inverse(c.T_base_cam) @ G @ est[c.name].T_base_cam
            mm, deg = 1000 * np.linalg.norm(rel[:3, 3]), np.degrees(geo.rotation_angle(rel[:3, :3]))
            self.assertLess(mm, TOL_REL_MM, f"{c.name}: {mm:.2f} mm relative to the ring\n{self.response.message}")
            self.assertLess(deg, TOL_REL_DEG, f"{c.name}: {deg:.3f} deg relative to the ring\n{self.response.message}")
            direct = geo.inverse(c.T_base_cam) @ est[c.name].T_base_cam
            self.assertLess(np.degrees(geo.rotation_angle(direct[:3, :3])), TOL_BASE_DEG, c.name)
            self.assertLess(1000 * np.linalg.norm(direct[:2, 3]), TOL_BASE_XY_MM, c.name)
            self.assertGreater(min(est[c.name].extrinsics_std), 0.0, c.name)

    def test_2_tf_carries_the_calibration(self):
        est = CameraRing.load(self.ring_file)
        for c in est:
            ts = self.tf_buffer.lookup_transform(est.base_frame, c.frame_id, rospy.Time(0), rospy.Duration(5.0))
            q, p = ts.transform.rotation, ts.transform.translation
            T = geo.transform_from_translation_quaternion([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
            dt, dr = geo.pose_distance(T, c.T_base_cam)
            self.assertLess(dt, TOL_TF, f"{c.name}: tf is {1000 * dt:.2f} mm from the calibrated ring file")
            self.assertLess(dr, TOL_TF, f"{c.name}: tf is {np.degrees(dr):.3f} deg from the calibrated ring file")

    def test_3_map_built_with_the_calibration(self):
        m = MarkerMap.load(self.map_file)
        truth = self.scene.truth_map()
        self.assertGreaterEqual(len([i for i in m.ids if i in truth]), 8, m.ids)
        fit = map_error(m, truth, best_fit=True)
        self.assertLess(fit["position_max_mm"], TOL_FIT_MAX_MM, format_map_error(fit))
        # The map's refined extrinsics start from the calibration (priors of a few mm around it).
        est = CameraRing.load(self.ring_file)
        for c, T in m.ring_extrinsics.items():
            dt, dr = geo.pose_distance(T, est[c].T_base_cam)
            self.assertLess(dt, 0.005, c)
            self.assertLess(np.degrees(dr), 0.5, c)


if __name__ == "__main__":
    rostest.rosrun(PKG, "mapper_calibrate", MapperCalibrateTest)
