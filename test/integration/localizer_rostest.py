#!/usr/bin/env python3
"""rostest node for localizer.test: plays the simulated ring (corners mode) and checks ~pose.

This node owns /clock (use_sim_time) and publishes, for each camera, ``ring/camK/camera_info``
and ``ring/camK/fiducial_vertices`` from :class:`RingSimulator` (true rig = the ring file with
a seeded 2 mm / 0.2 deg calibration error), 10 frames per simulated second, while the robot
moves. Named ``*_rostest.py`` so pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import threading
import time
import unittest

import numpy as np
import rospkg
import rospy
import rostest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.srv import GetMap
from rosgraph_msgs.msg import Clock, Log

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import model_to_camera_info, observations_to_fiducials
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

PKG = "aruco_ring_localization"
TOL_M = 0.03
TOL_YAW = np.radians(1.0)


def _path(t: float) -> np.ndarray:
    """Robot pose (x, y, yaw) at time t (s): a slow arc on the plate."""
    return np.array([4.6 + 0.8 * np.sin(0.2 * t), 4.4 + 0.5 * np.sin(0.13 * t), geo.wrap_angle(0.25 * t)])


class LocalizerSimTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("localizer_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.scene = Scene.default()
        cls.ring = CameraRing.load(f"{root}/config/ring.yaml")
        cls.sim = RingSimulator(cls.scene, perturb_ring(cls.ring, seed=0), pixel_noise=0.3, seed=1)
        cls.clock_pub = rospy.Publisher("/clock", Clock, queue_size=10)
        cls.pubs = {}
        for cam in cls.ring.cameras:
            cls.pubs[cam.name] = (rospy.Publisher(f"{cam.namespace}/fiducial_vertices", FiducialArray, queue_size=10),
                                  rospy.Publisher(f"{cam.namespace}/camera_info",
                                                  type(model_to_camera_info(cam.model)), queue_size=2, latch=True))
        cls.poses = []
        cls.lock = threading.Lock()
        rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, cls._on_pose, queue_size=50)
        cls.diags = []  # (stamp, {name: DiagnosticStatus}) of each /diagnostics array
        rospy.Subscriber("/diagnostics", DiagnosticArray, cls._on_diag, queue_size=50)
        cls.truth = {}

    @classmethod
    def _on_pose(cls, msg):
        q = msg.pose.pose.orientation
        yaw = np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        with cls.lock:
            cls.poses.append((msg.header.stamp.to_sec(), msg.pose.pose.position.x, msg.pose.pose.position.y, yaw))

    @classmethod
    def _on_diag(cls, msg):
        with cls.lock:
            cls.diags.append((msg.header.stamp.to_sec(), {st.name: st for st in msg.status}))

    def _expected(self) -> set:
        """The statuses of a full array: every camera, the filter and, with marker_check/enabled (the
        default), the moved-marker check's."""
        names = {f"localizer: camera {n}" for n in self.ring.names} | {"localizer: filter"}
        if rospy.get_param("/localizer/marker_check/enabled", True):
            names.add("localizer: markers")
        return names

    def _diags_between(self, a: float, b: float):
        """The full arrays (every camera, the filter, the marker check) stamped in [a, b)."""
        n = len(self._expected())
        with self.lock:
            return [d for t, d in self.diags if a <= t < b and len(d) == n]

    def _play(self, t0: float, t1: float, path_t0: float = 0.0, cameras=None, rate_hz: float = 10.0, infos=None):
        """Publish clock + detections from sim time t0 to t1 (robot at _path(t - t0 + path_t0));
        ``infos``: camera_info messages to send instead of the ring file's, by camera."""
        cameras = cameras or self.ring.names
        n = int(round((t1 - t0) * rate_hz))
        for k in range(n):
            t = t0 + k / rate_hz
            stamp = rospy.Time.from_sec(t)
            self.clock_pub.publish(Clock(clock=stamp))
            pose = _path(t - t0 + path_t0)
            self.truth[round(t, 3)] = pose
            frame = self.sim.observe(self.scene.T_world_base(pose), t)
            for name in cameras:
                fv, ci = self.pubs[name]
                info = (infos or {}).get(name) or model_to_camera_info(self.ring[name].model, self.ring[name].frame_id)
                info.header.stamp = stamp
                ci.publish(info)
                msg = FiducialArray()
                msg.header.stamp = stamp
                msg.header.frame_id = self.ring[name].frame_id
                msg.fiducials = observations_to_fiducials(frame.cameras[name].observations)
                fv.publish(msg)
            rospy.rostime.wallsleep(1.0 / rate_hz)  # real time: the assembler timeout is in wall time
        # let the last frames through (and the assembler's timeout for silent cameras)
        for k in range(1, 6):
            self.clock_pub.publish(Clock(clock=rospy.Time.from_sec(t1 + 0.1 * k)))
            rospy.rostime.wallsleep(0.1)

    def _poses_between(self, a: float, b: float):
        with self.lock:
            return [p for p in self.poses if a <= p[0] < b]

    def _errors(self, poses):
        out = []
        for t, x, y, yaw in poses:
            truth = self.truth.get(round(t, 3))
            if truth is not None:
                out.append((np.hypot(x - truth[0], y - truth[1]), abs(geo.angle_diff(yaw, truth[2]))))
        return np.array(out)

    def test_1_follows_ground_truth(self):
        # wait for subscriptions
        deadline = rospy.rostime.wallsleep
        for _ in range(50):
            if all(p[0].get_num_connections() > 0 for p in self.pubs.values()):
                break
            deadline(0.1)
        self._play(100.0, 106.0)
        poses = self._poses_between(101.0, 106.0)
        self.assertGreater(len(poses), 30, f"only {len(poses)} poses in 5 s of 10 Hz frames")
        err = self._errors(poses)
        self.assertLess(err[:, 0].max(), TOL_M, f"max position error {err[:, 0].max() * 100:.2f} cm")
        self.assertLess(err[:, 1].max(), TOL_YAW, f"max yaw error {np.degrees(err[:, 1].max()):.2f} deg")

    def test_2_keeps_publishing_with_seven_cameras_silent(self):
        self._play(107.0, 111.0, path_t0=7.0, cameras=["cam0"])
        poses = self._poses_between(107.5, 111.0)
        self.assertGreater(len(poses), 20, f"only {len(poses)} poses with one camera in 3.5 s")
        err = self._errors(poses)
        # One camera often sees a single far marker: a sanity bound, not the accuracy target.
        self.assertLess(err[:, 0].max(), 0.25, f"max position error with one camera {err[:, 0].max() * 100:.2f} cm")

    def test_3_time_jump_back_resets_the_filter(self):
        self._play(112.0, 114.0, path_t0=12.0)
        # The bag loops: time goes back to 20 s and the robot is back where it started.
        self._play(20.0, 24.0, path_t0=0.0)
        poses = self._poses_between(20.5, 24.0)
        self.assertGreater(len(poses), 20, f"only {len(poses)} poses after the time jump")
        err = self._errors(poses)
        self.assertLess(err[:, 0].max(), TOL_M, f"after the jump: max position error {err[:, 0].max() * 100:.2f} cm")

    def test_4_every_camera_silent_is_an_error(self):
        # only the clock moves: no detections from any camera for 4 s
        for k in range(40):
            self.clock_pub.publish(Clock(clock=rospy.Time.from_sec(30.0 + 0.1 * k)))
            rospy.rostime.wallsleep(0.1)
        diags = self._diags_between(32.0, 34.0)
        self.assertTrue(diags, "no /diagnostics array stamped 32-34 s while every camera was silent")
        last = diags[-1]
        self.assertEqual(last["localizer: filter"].level, DiagnosticStatus.ERROR, last["localizer: filter"].message)
        for name in self.ring.names:
            self.assertEqual(last[f"localizer: camera {name}"].level, DiagnosticStatus.WARN)

    def test_5_diagnostics_follow_diagnostic_updater_conventions(self):
        full = self._diags_between(100.0, 200.0)
        self.assertGreater(len(full), 5, f"only {len(full)} full /diagnostics arrays in tests 1-3")
        expected = self._expected()
        for d in full:
            self.assertEqual(set(d), expected)
            if "localizer: markers" in d:   # no marker moved here: the check must not declare one
                self.assertEqual(d["localizer: markers"].level, DiagnosticStatus.OK, d["localizer: markers"].message)
            for name in self.ring.names:
                self.assertEqual(d[f"localizer: camera {name}"].hardware_id, name)
            self.assertTrue(d["localizer: filter"].hardware_id)
        # 1 Hz on the node's (simulated) clock
        with self.lock:
            stamps = np.array(sorted(t for t, d in self.diags if 100.0 <= t < 106.0 and len(d) == len(expected)))
        self.assertGreater(len(stamps), 2)
        self.assertAlmostEqual(float(np.median(np.diff(stamps))), 1.0, delta=0.2)
        # tracking with 8 cameras: OK; with 7 silent (test 2, after silent_after): WARN for them, cam0 OK
        self.assertEqual(self._diags_between(103.0, 106.0)[-1]["localizer: filter"].level, DiagnosticStatus.OK)
        silent = self._diags_between(109.0, 111.5)
        self.assertTrue(silent, "no /diagnostics array stamped 109-111.5 s (7 cameras silent)")
        self.assertEqual(silent[-1]["localizer: camera cam0"].level, DiagnosticStatus.OK)
        for name in self.ring.names[1:]:
            self.assertEqual(silent[-1][f"localizer: camera {name}"].level, DiagnosticStatus.WARN, name)

    def test_6_static_map_service_gives_the_marker_grid(self):
        rospy.wait_for_service("/localizer/static_map", timeout=30.0)
        grid = rospy.ServiceProxy("/localizer/static_map", GetMap)().map
        marker_map = MarkerMap.load(f"{rospkg.RosPack().get_path(PKG)}/test/data/lab_truth_map.yaml")
        self.assertEqual(grid.header.frame_id, marker_map.frame_id)
        self.assertAlmostEqual(grid.info.resolution, 0.05, places=6)
        data = np.array(grid.data, np.int8).reshape(grid.info.height, grid.info.width)
        self.assertEqual(set(np.unique(data).tolist()), {-1, 100})
        res, ox, oy = grid.info.resolution, grid.info.origin.position.x, grid.info.origin.position.y
        for e in marker_map:
            x, y = e.T_map_marker[:2, 3]
            self.assertEqual(data[int((y - oy) // res), int((x - ox) // res)], 100, f"marker {e.marker_id}'s cell")
        # the markers are a small part of the room
        self.assertLess(np.count_nonzero(data == 100), 0.2 * data.size)

    def test_7_a_changed_camera_info_is_applied_within_the_check_period(self):
        """The camera_info connections pause input/camera_info_check_period after a repeat of the
        camera_info in force (each camera sent the same one with every frame so far); a changed one
        is still applied within that period, through a real master and rospy's sockets."""
        period = rospy.get_param("/localizer/input/camera_info_check_period")
        self.assertGreater(period, 0.0, "the check period is off: nothing to test")
        logged = []   # (wall time received, text) of the localizer's lines about cam0's intrinsics

        def on_log(msg):
            if msg.name == "/localizer" and "cam0 intrinsics from camera_info" in msg.msg:
                logged.append((time.monotonic(), msg.msg))

        sub = rospy.Subscriber("/rosout", Log, on_log, queue_size=100)   # every node's log lines, the localizer's too
        for _ in range(100):
            if sub.get_num_connections() > 1:   # ours (rospy's own /rosout publisher) and at least the localizer
                break
            rospy.rostime.wallsleep(0.1)
        self._play(40.0, 41.0)      # the same camera_info again: every connection pauses
        info = model_to_camera_info(self.ring["cam0"].model, self.ring["cam0"].frame_id)
        K = list(info.K)
        K[0] *= 1.01
        info.K = K
        start = time.monotonic()
        self._play(41.0, 41.0 + period + 2.0, path_t0=1.0, infos={"cam0": info})
        sub.unregister()
        new = [(t - start, text) for t, text in logged if f"fx {K[0]:.3f}" in text]
        self.assertTrue(new, f"cam0's changed camera_info (fx {K[0]:.3f}) not applied within {period + 2.0:.1f} s "
                             f"of 10 Hz camera_info (check period {period} s); logged: {logged}")
        rospy.loginfo("localizer_rostest: the changed camera_info was applied %.2f s after it was first sent "
                      "(check period %.1f s)", new[0][0], period)


if __name__ == "__main__":
    rostest.rosrun(PKG, "localizer_sim", LocalizerSimTest)
