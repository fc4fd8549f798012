#!/usr/bin/env python3
"""rostest node of motion.test: free-running cameras and odometry through the stock localization.launch.

This node owns /clock (use_sim_time) and plays the simulated lab (corners mode, the exact rig, the
true map) while the robot drives a circle at about 0.5 m/s: every 20 ms of simulated time a wheel
odometry message on ``odom`` (its own origin, a 1 % scale error, pose and twist); every 100 ms the
8 cameras' detections, camera k exposing ``phase_k`` before the frame's time (phases spread over
80 ms, 2 ms jitter) and stamped with that exposure time. After each camera frame it waits (wall
clock, generous timeout) for the localizer's ``~camera_estimates``, which the localizer publishes
for camera frames only: the pace follows the node, whatever the machine's load.

Checks: the pose comes out at the odometry rate; with free-running cameras the poses of camera
frames are within 1 cm (median) of the truth at their stamps; during a 5 s marker blackout (the
cameras report, without markers) the pose keeps coming at the odometry rate and is within 5 cm
at its end, although the odometry resets 1 m away in the middle of it (``ODOM_JUMP``: a hostile or
broken odometry must not move the robot); the markers back, the track is the cameras' again.

With ``~six_dof`` (motion6.test: ``model:=6dof``, the 6-DOF tracker) the cameras are
synchronized (the 6-DOF tracker does not compensate free-running cameras) and the blackout checks
are the tracker's: its pose comes at the odometry rate too, but only up to ``tracker6/max_coast``
after the last accepted measurement, none after that until the markers are back.

With ``~odom_body`` ([x, y, yaw_deg], motion_body.test) the odometry is that of a body mounted
there on the robot (``child_frame_id`` odom_body, a static tf base_link -> odom_body in the .test
file), as a visual-inertial odometry reports its IMU's: the same checks hold only if the localizer
makes it base_link's through tf.
Named ``*_rostest.py`` so pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import threading
import time
import unittest

import numpy as np
import rospkg
import rospy
import rostest
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.detections import MarkerObservation
from aruco_ring_localization.odometry import se2_between, se2_compose
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import model_to_camera_info, observations_to_fiducials, pose_to_msg
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Scene

PKG = "aruco_ring_localization"
T0 = 100.0
CAMERA_PERIOD = 0.1
ODOM_PERIOD = 0.02
ANSWER_TIMEOUT = 10.0   # wall s: a loaded machine answers in tens of ms
#: (sim time since T0, x shift m): the odometry's pose jumps there (in the blackout), as a reset does.
ODOM_JUMP = (10.51, 1.0)


def _truth(t: float) -> np.ndarray:
    """(x, y, yaw) at sim time t: a circle of 0.8 m radius at 0.6 rad/s (0.48 m/s), turning slowly."""
    a = 0.6 * (t - T0)
    return np.array([4.6 + 0.8 * np.cos(a), 4.4 + 0.8 * np.sin(a), geo.wrap_angle(0.25 * (t - T0))])


class MotionTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("motion_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.scene = Scene.default()
        cls.ring = CameraRing.load(f"{root}/config/ring.yaml")
        cls.sim = RingSimulator(cls.scene, cls.ring, pixel_noise=0.3, seed=1)
        cls.rng = np.random.default_rng(2)
        n = len(cls.ring.names)
        cls.six_dof = bool(rospy.get_param("~six_dof", False))
        cls.phases = cls.rng.permutation(np.linspace(0.0, 0.08, n))
        if cls.six_dof:
            cls.phases = np.zeros(n)
        cls.clock_pub = rospy.Publisher("/clock", Clock, queue_size=10)
        cls.odom_pub = rospy.Publisher("odom", Odometry, queue_size=20)
        cls.pubs = {}
        for cam in cls.ring.cameras:
            cls.pubs[cam.name] = (rospy.Publisher(f"{cam.namespace}/fiducial_vertices", FiducialArray, queue_size=10),
                                  rospy.Publisher(f"{cam.namespace}/camera_info",
                                                  type(model_to_camera_info(cam.model)), queue_size=2, latch=True))
        cls.lock = threading.Lock()
        cls.answered = threading.Condition(cls.lock)
        cls.poses = []          # (stamp, x, y, yaw)
        cls.last_estimates = -1.0
        rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, cls._on_pose, queue_size=200)
        rospy.Subscriber("/localizer/camera_estimates", PoseArray, cls._on_estimates, queue_size=20)
        cls.odom = np.array([-2.0, 1.0, 0.5])   # the odometry's own origin
        body = rospy.get_param("~odom_body", [])
        cls.body = None if not body else np.array([float(body[0]), float(body[1]), np.radians(float(body[2]))])
        cls.prev_truth = _truth(T0)
        cls.unanswered = 0
        end = time.monotonic() + 60.0
        while time.monotonic() < end and not (
                all(p[0].get_num_connections() > 0 for p in cls.pubs.values()) and cls.odom_pub.get_num_connections()):
            time.sleep(0.1)
        cls._play(T0, T0 + 8.0)
        cls._play(T0 + 8.0, T0 + 13.0, dark=True)
        cls._play(T0 + 13.0, T0 + 16.0)

    @classmethod
    def _on_pose(cls, msg):
        q = msg.pose.pose.orientation
        yaw = np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        with cls.lock:
            cls.poses.append((msg.header.stamp.to_sec(), msg.pose.pose.position.x, msg.pose.pose.position.y, yaw))

    @classmethod
    def _on_estimates(cls, msg):
        with cls.answered:
            cls.last_estimates = max(cls.last_estimates, msg.header.stamp.to_sec())
            cls.answered.notify_all()

    @classmethod
    def _clock(cls, t: float) -> None:
        cls.clock_pub.publish(Clock(clock=rospy.Time.from_sec(t)))

    @classmethod
    def _play(cls, t0: float, t1: float, dark: bool = False) -> None:
        k0, k1 = int(round((t0 - T0) / ODOM_PERIOD)), int(round((t1 - T0) / ODOM_PERIOD))
        for k in range(k0 + 1, k1 + 1):
            t = T0 + k * ODOM_PERIOD
            truth = _truth(t)
            step = se2_between(cls.prev_truth, truth)
            cls.prev_truth = truth
            cls.odom = se2_compose(cls.odom, step * np.array([1.01, 1.01, 1.01]))
            if t - ODOM_PERIOD < T0 + ODOM_JUMP[0] <= t:
                cls.odom = cls.odom + np.array([ODOM_JUMP[1], 0.0, 0.0])
            cls._clock(t)
            od = Odometry()
            od.header.stamp = rospy.Time.from_sec(t)
            od.header.frame_id = "odom"
            v, w = np.array([step[0], step[1], 0.0]) / ODOM_PERIOD, float(step[2] / ODOM_PERIOD)
            if cls.body is None:
                od.child_frame_id = "base_link"
                od.pose.pose = pose_to_msg(geo.transform_from_se2(*cls.odom))
            else:   # the mounted body's pose, and its twist in its own frame (nav_msgs)
                od.child_frame_id = "odom_body"
                od.pose.pose = pose_to_msg(geo.transform_from_se2(*se2_compose(cls.odom, cls.body)))
                v_body = v + np.cross([0.0, 0.0, w], [cls.body[0], cls.body[1], 0.0])
                c, s_ = np.cos(cls.body[2]), np.sin(cls.body[2])
                v = np.array([c * v_body[0] + s_ * v_body[1], -s_ * v_body[0] + c * v_body[1], 0.0])
            od.twist.twist.linear.x, od.twist.twist.linear.y = float(v[0]), float(v[1])
            od.twist.twist.angular.z = w
            cls.odom_pub.publish(od)
            time.sleep(0.003)
            if k % int(round(CAMERA_PERIOD / ODOM_PERIOD)) == 0:
                cls._camera_frame(t, dark)

    @classmethod
    def _camera_frame(cls, t: float, dark: bool) -> None:
        with cls.lock:
            before = cls.last_estimates
        for c, name in enumerate(cls.ring.names):
            ts = t - cls.phases[c] + float(np.clip(cls.rng.normal(0.0, 0.002), -0.005, 0.005))
            T = Scene.T_world_base(_truth(ts))
            obs = [] if dark else [MarkerObservation(m, px + cls.rng.normal(0.0, 0.3, px.shape))
                                   for m, px in cls.sim.visible_camera(T, name)]
            fv, ci = cls.pubs[name]
            info = model_to_camera_info(cls.ring[name].model, cls.ring[name].frame_id)
            info.header.stamp = rospy.Time.from_sec(ts)
            ci.publish(info)
            msg = FiducialArray()
            msg.header.stamp = rospy.Time.from_sec(ts)
            msg.header.frame_id = cls.ring[name].frame_id
            msg.fiducials = observations_to_fiducials(obs)
            fv.publish(msg)
        if dark and cls.six_dof:
            time.sleep(0.05)   # the 6-DOF tracker publishes nothing for a frame without markers
            return
        with cls.answered:
            ok = cls.answered.wait_for(lambda: cls.last_estimates > before, timeout=ANSWER_TIMEOUT)
        cls.unanswered += int(not ok)

    def _between(self, a: float, b: float):
        with self.lock:
            return [p for p in self.poses if T0 + a <= p[0] < T0 + b]

    @staticmethod
    def _errors(poses) -> np.ndarray:
        return np.array([np.hypot(x - _truth(t)[0], y - _truth(t)[1]) for t, x, y, _ in poses])

    def test_1_pose_at_the_odometry_rate(self):
        poses = self._between(2.0, 8.0)
        rate = len(poses) / 6.0
        self.assertGreaterEqual(rate, 45.0, f"{rate:.1f} poses per second with odometry at 50 Hz "
                                            f"({self.unanswered} camera frames unanswered)")

    def test_2_free_running_cameras_compensated(self):
        err = self._errors(self._between(2.0, 8.0))   # camera frames and odometry steps alike
        self.assertGreater(len(err), 100)
        self.assertLess(float(np.median(err)), 0.01, f"median error {np.median(err) * 100:.2f} cm")
        self.assertLess(float(np.max(err)), 0.03, f"max error {np.max(err) * 100:.2f} cm")

    def test_3_blackout_bridged_by_odometry(self):
        if self.six_dof:
            # The last markers at 8.0 s; the tracker coasts along the odometry for max_coast (0.25 s)
            # after its last accepted measurement, the frame of 8.0 s or at worst of 7.9 s: at least
            # the 7 odometry poses of 8.02-8.14 s.
            steps = [(p[0] - T0) / ODOM_PERIOD for p in self._between(8.01, 8.26)]
            coast = [k for k in steps if abs(k - round(k)) < 1e-3]     # the odometry's stamps
            self.assertGreaterEqual(len(coast), 7, f"{len(coast)} odometry poses in the 0.25 s after the last markers")
            late = self._between(8.4, 13.0)
            self.assertEqual(len(late), 0, f"{len(late)} poses published 0.4-5 s into the blackout")
            after = self._errors(self._between(14.0, 16.0))
            self.assertGreater(len(after), 90)
            self.assertLess(float(np.median(after)), 0.01, f"after the blackout: median {np.median(after) * 100:.2f} cm")
            return
        dark = self._between(8.5, 13.0)
        self.assertGreaterEqual(len(dark) / 4.5, 45.0, f"{len(dark)} poses in 4.5 s of blackout")
        end = self._errors(self._between(12.8, 13.0))
        self.assertTrue(len(end), "no pose at the end of the blackout")
        self.assertLess(float(end.max()), 0.05, f"error at the end of a 5 s blackout {end.max() * 100:.2f} cm")
        after = self._errors(self._between(14.0, 16.0))
        self.assertLess(float(np.median(after)), 0.01, f"after the blackout: median {np.median(after) * 100:.2f} cm")


if __name__ == "__main__":
    rostest.rosrun(PKG, "motion", MotionTest)
