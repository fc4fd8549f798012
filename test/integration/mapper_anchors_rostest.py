#!/usr/bin/env python3
"""rostest node for mapper_anchors.test: the mapper (stock mapping.launch) in a surveyed frame.

The simulator node jumps the robot to each of the lab's mapping stations (corners mode, 0.3 px
noise, a seeded calibration error of the true rig); once it has held the last one, ``~save_map``
is called. The map must be in the frame of the anchors file (frame convention ``survey``; its
anchors are 3 markers of config/lab_scene.yaml at their true centres plus 1 mm noise, so that
frame is the simulator's world frame): compared with the truth *without any alignment*, and each
anchor's residual recorded and within its survey noise. Named ``*_rostest.py`` so pytest does not
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
from std_srvs.srv import Trigger

from aruco_ring_localization.anchors import load_anchors
from aruco_ring_localization.config import load_config
from aruco_ring_localization.evaluation.maps import format_map_error, map_error
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.simulation.simulator import SimulatorCore
from sim_route import HeldWaypoints

PKG = "aruco_ring_localization"
# Strict (no alignment) error of the surveyed map: the map's geometry (best fit ~1-2 mm) plus the
# frame's error from 1 mm anchors ~10 m apart (< 1 mm). In the reference marker's frame the same
# run is off by tens of mm (mapper.test bounds it at 60 mm RMS).
TOL_STRICT_MAX_MM = 10.0
TOL_ANCHOR_SIGMAS = 4.0


class MapperAnchorsTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("mapper_anchors_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.map_file = rospy.get_param("/mapper/map_file")
        cls.anchors_file = rospy.get_param("/mapper/map/anchors_file")
        shutil.rmtree(os.path.dirname(cls.map_file), ignore_errors=True)
        config = load_config(SimulatorConfig, rospy.get_param("/simulator"), source="/simulator")
        cls.scene = Scene.load(config.scene.file)
        cls.core = SimulatorCore(config, cls.scene, CameraRing.load(f"{root}/config/ring.yaml"))
        cls.stations = cls.core.waypoints()
        HeldWaypoints().wait_for_route_end(len(cls.stations) - 1, timeout=110.0)
        rospy.wait_for_service("/mapper/save_map", timeout=30.0)
        cls.response = rospy.ServiceProxy("/mapper/save_map", Trigger)()

    def test_0_the_anchors_file_is_the_scenes(self):
        """lab_anchors.yaml is made from config/lab_scene.yaml (its header says how): if the scene
        changed, regenerate it, else this test would measure a survey of another lab."""
        truth = self.scene.truth_map()
        for a in load_anchors(self.anchors_file).anchors:
            self.assertIn(a.marker_id, truth, f"anchor marker {a.marker_id} is not in {self.scene.name}")
            d = float(np.linalg.norm(truth.T_map_marker(a.marker_id)[:3, 3] - a.position))
            self.assertLess(d, 0.006, f"anchor {a.marker_id} is {1000 * d:.1f} mm from the scene's marker: "
                                      f"regenerate {self.anchors_file} (its header)")

    def test_1_map_in_the_surveyed_frame(self):
        self.assertTrue(self.response.success, f"save_map failed: {self.response.message}")
        self.assertIn("surveyed frame", self.response.message)
        m = MarkerMap.load(self.map_file)
        self.assertEqual(m.frame_convention, "survey")
        self.assertIsNone(m.reference_marker)
        self.assertEqual(m.anchors["source"], self.anchors_file)
        truth = self.scene.truth_map()
        common = [i for i in m.ids if i in truth]
        self.assertGreaterEqual(len(common), 5, f"only {len(common)} markers mapped: {m.ids}")
        strict = map_error(m, truth)   # surveyed frame = the world frame: no alignment at all
        self.assertEqual(strict["alignment"], "reference")
        np.testing.assert_allclose(strict["T_truth_est"], np.eye(4))
        self.assertLess(strict["position_max_mm"], TOL_STRICT_MAX_MM, format_map_error(strict))

    def test_2_anchor_residuals(self):
        m = MarkerMap.load(self.map_file)
        points = m.anchors["points"]
        self.assertEqual(sorted(p["marker"] for p in points), sorted(load_anchors(self.anchors_file).ids))
        for p in points:
            self.assertIn("residual", p, f"anchor {p['marker']} not mapped")
            self.assertLess(p["residual_sigmas"], TOL_ANCHOR_SIGMAS, f"anchor {p}")


if __name__ == "__main__":
    rostest.rosrun(PKG, "mapper_anchors", MapperAnchorsTest)
