#!/usr/bin/env python3
"""rostest node for mapper.test: maps the simulated lab through the mapper node.

The simulator node (mapper.test: corners mode, 0.3 px noise, true rig = the ring file with a
seeded 2 mm / 0.2 deg calibration error, owning ``/clock``) jumps the robot to each of the lab's
mapping stations and holds it there 2 s, publishing ``ring/camK/camera_info`` and
``ring/camK/fiducial_vertices``; once it has held the last one (``sim/at_waypoint``), ``~save_map``
is called and the written map file, the static tf ``map -> marker_<id>`` and ``~markers`` are
checked. Named ``*_rostest.py`` so pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import os
import re
import shutil
import threading
import unittest

import rospkg
import rospy
import rostest
import tf2_ros
from rosgraph_msgs.msg import Log
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import load_config
from aruco_ring_localization.evaluation.maps import format_map_error, map_error
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import msg_to_transform, pose_msg_to_transform
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.simulation.simulator import SimulatorCore
from sim_route import HeldWaypoints

PKG = "aruco_ring_localization"
TOL_FIT_MAX_MM = 10.0        # best-fit (the map's geometry): measured ~1-2 mm
TOL_OWN_RMS_MM = 60.0        # in the map's own frame (adds the frame's heading error): sanity bound
TOL_TF = 1e-6


class MapperSimTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("mapper_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.map_file = rospy.get_param("/mapper/map_file")
        shutil.rmtree(os.path.dirname(cls.map_file), ignore_errors=True)
        # The simulator's own parameters: the same true rig and stations as the node's.
        config = load_config(SimulatorConfig, rospy.get_param("/simulator"), source="/simulator")
        ring = CameraRing.load(f"{root}/config/ring.yaml")
        cls.base_frame = ring.base_frame
        cls.core = SimulatorCore(config, Scene.default(), ring)
        cls.stations = cls.core.waypoints()
        cls.lock = threading.Lock()
        cls.marker_arrays = []
        cls.progress = []   # the mapper's progress lines (/rosout)
        rospy.Subscriber("/rosout", Log, cls._on_log, queue_size=100)
        rospy.Subscriber("/mapper/markers", MarkerArray, cls._on_markers, queue_size=5)
        HeldWaypoints().wait_for_route_end(len(cls.stations) - 1, timeout=90.0)
        rospy.wait_for_service("/mapper/save_map", timeout=30.0)
        cls.response = rospy.ServiceProxy("/mapper/save_map", Trigger)()
        cls.tf_buffer = tf2_ros.Buffer()
        cls.tf_listener = tf2_ros.TransformListener(cls.tf_buffer)

    @classmethod
    def _on_log(cls, msg):
        if msg.name == "/mapper" and " markers mapped from " in msg.msg:   # the progress lines
            with cls.lock:
                cls.progress.append(msg.msg)

    @classmethod
    def _on_markers(cls, msg):
        with cls.lock:
            cls.marker_arrays.append(msg)

    def _visible_truth(self) -> MarkerMap:
        """The truth restricted to the markers some camera sees from some station."""
        sim = self.core.sim
        seen = {mid for st in self.stations for views in sim.visible(Scene.T_world_base(st)).values()
                for mid, _ in views}
        truth = self.core.scene.truth_map()
        for mid in list(truth.ids):
            if mid not in seen:
                truth.remove(mid)
        return truth

    def test_1_saved_map_matches_the_truth(self):
        self.assertTrue(self.response.success, f"save_map failed: {self.response.message}")
        self.assertIn(self.map_file, self.response.message)
        m = MarkerMap.load(self.map_file)
        truth = self._visible_truth()
        self.assertGreaterEqual(len(truth), 5, f"only {len(truth)} markers visible: test setup broken")
        missing = [i for i in truth.ids if i not in m]
        self.assertEqual(missing, [], f"visible markers missing from the map: {missing}; {self.response.message}")
        fit = map_error(m, truth, best_fit=True)
        self.assertLess(fit["position_max_mm"], TOL_FIT_MAX_MM, format_map_error(fit))
        own = map_error(m, truth)
        self.assertLess(own["position_rms_mm"], TOL_OWN_RMS_MM, format_map_error(own))
        self.assertEqual(m.method, "refined")

    def test_2_static_tf_of_every_marker(self):
        m = MarkerMap.load(self.map_file)
        bad = []
        for e in m:
            try:
                ts = self.tf_buffer.lookup_transform(m.frame_id, f"marker_{e.marker_id}", rospy.Time(0),
                                                     rospy.Duration(5.0))
            except (tf2_ros.LookupException, tf2_ros.ExtrapolationException, tf2_ros.ConnectivityException) as exc:
                bad.append((e.marker_id, str(exc)))
                continue
            dp, dr = geo.pose_distance(msg_to_transform(ts.transform), e.T_map_marker)
            if dp > TOL_TF or dr > TOL_TF:
                bad.append((e.marker_id, f"tf differs from the file by {dp:.2e} m, {dr:.2e} rad"))
        self.assertEqual(bad, [], f"static tf {m.frame_id} -> marker_<id>: {bad}")

    def test_3_marker_array_shows_every_marker(self):
        m = MarkerMap.load(self.map_file)
        deadline = rospy.Time.now() + rospy.Duration(5.0)
        while not rospy.is_shutdown():
            with self.lock:
                last = self.marker_arrays[-1] if self.marker_arrays else None
            if last is not None or rospy.Time.now() > deadline:
                break
            rospy.rostime.wallsleep(0.1)
        self.assertIsNotNone(last, "no ~markers message")
        cubes = [mk for mk in last.markers if mk.type == Marker.CUBE and mk.action == Marker.ADD]
        labels = {int(mk.text.split()[0]) for mk in last.markers if mk.type == Marker.TEXT_VIEW_FACING}
        self.assertEqual(len(cubes), len(m), f"{len(cubes)} boxes for {len(m)} markers")
        missing = [i for i in m.ids if i not in labels]
        self.assertEqual(missing, [], f"markers without an id label: {missing}")
        frames = {mk.header.frame_id for mk in last.markers if mk.action == Marker.ADD}
        self.assertEqual(frames, {m.frame_id}, f"marker frames {frames}")
        # The boxes sit where the file says (the saved, refined map is what is shown).
        worst = max(geo.pose_distance(pose_msg_to_transform(mk.pose), m.T_map_marker(mk.id // 2))[0] for mk in cubes)
        self.assertLess(worst, 1e-6, f"a box is {worst:.2e} m from its marker in the file")

    def test_5_progress_does_not_call_cameras_silent_while_frames_arrive(self):
        with self.lock:
            lines = list(self.progress)
        self.assertGreaterEqual(len(lines), 2, f"too few progress lines: {lines}")
        counts = [int(re.search(r"from (\d+) frames", line).group(1)) for line in lines]
        for before, after, line in zip(counts, counts[1:], lines[1:]):
            if after > before:
                self.assertNotIn("silent cameras", line, f"frames {before} -> {after}, yet: {line}")


if __name__ == "__main__":
    rostest.rosrun(PKG, "mapper_sim", MapperSimTest)
