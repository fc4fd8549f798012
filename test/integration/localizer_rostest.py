#!/usr/bin/env python3
"""rostest node for localizer.test: plays the simulated ring (corners mode) and checks ~pose.

This node owns /clock (use_sim_time) and publishes, for each camera, ``ring/camK/camera_info``
and ``ring/camK/fiducial_vertices`` from :class:`RingSimulator` (true rig = the ring file with
a seeded 2 mm / 0.2 deg calibration error), 10 frames per simulated second, while the robot
moves. Named ``*_rostest.py`` so pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import threading
import unittest

import numpy as np
import rospkg
import rospy
import rostest
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rosgraph_msgs.msg import Clock

from aruco_ring_localization import geometry as geo
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
        cls.truth = {}

    @classmethod
    def _on_pose(cls, msg):
        q = msg.pose.pose.orientation
        yaw = np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        with cls.lock:
            cls.poses.append((msg.header.stamp.to_sec(), msg.pose.pose.position.x, msg.pose.pose.position.y, yaw))

    def _play(self, t0: float, t1: float, path_t0: float = 0.0, cameras=None, rate_hz: float = 10.0):
        """Publish clock + detections from sim time t0 to t1 (robot at _path(t - t0 + path_t0))."""
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
                info = model_to_camera_info(self.ring[name].model, self.ring[name].frame_id)
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


if __name__ == "__main__":
    rostest.rosrun(PKG, "localizer_sim", LocalizerSimTest)
