#!/usr/bin/env python3
"""rostest node of identity_localization.test and identity_mapping.test: the node live, then the
bag tool offline on what was recorded, must give the same answer.

Through a real master and the stock launch files (localization.launch or mapping.launch, started
by the .test file): this node starts the simulated lab (simulation.launch, corners mode, wall
time) in a subprocess under the namespace ``sim_raw`` and relays its topics (the messages as
they are) to their usual names. The relay is what makes the start identical for the node and
for ``rosbag record``: it passes nothing on until both are connected to every relayed topic (a
ROS 1 subscriber misses what is published before its connection is made, and each subscriber
connects at its own time), and it opens and closes between two ring frames, never inside one. Before the first
detection it publishes each camera's camera_info once (latched, the simulator's content), so
both have the intrinsics first (which topic's callback runs first is up to ROS, not to us).

* localization: the recording (detections, camera_info, /tf_static, cmd_vel, odom and the
  localizer's ``~pose``) goes through ``aruco_ring localize``; every recorded pose must be in its
  output with the same stamp, x, y, z and yaw to 1e-9, and no offline pose may be missing in
  between. The localizer's diagnostics must say it dropped no frame and processed every ring
  frame with all 8 cameras (the simulator runs at 5 Hz so that even a loaded machine keeps up);
  a failure prints them, so a dropped frame is explained, not ignored.
* mapping: the robot visits the lab's 5 mapping stations; the mapper's ``~save_map`` file must equal
  ``aruco_ring build-map`` on the recording: the same markers, reference and poses to 1e-9.

Named ``*_rostest.py`` so pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import unittest
from typing import Dict, List, Optional

import numpy as np
import rosbag
import rosgraph
import rospkg
import rospy
import rostest
from diagnostic_msgs.msg import DiagnosticArray
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Int32
from std_srvs.srv import Trigger

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import model_to_camera_info, pose_msg_to_transform

PKG = "aruco_ring_localization"
TOL = 1e-9
RATE_HZ = 5.0
RECORDER = "identity_record"
RAW = "/sim_raw"


def _subscribers(topic: str) -> List[str]:
    _, subs, _ = rosgraph.Master("/identity_rostest").getSystemState()
    return next((nodes for t, nodes in subs if t == topic), [])


def _wait(what: str, ok, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while not ok():
        if time.monotonic() > end or rospy.is_shutdown():
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


class _Process:
    """A subprocess in its own process group, ended with SIGINT (as Ctrl-C would)."""

    def __init__(self, args: List[str], log: str):
        self.log = open(log, "w")
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=self.log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def stop(self, timeout: float = 30.0) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.log.close()


class IdentityTest(unittest.TestCase):
    mode = "localization"

    @classmethod
    def setUpClass(cls):
        rospy.init_node("identity_rostest")
        cls.root = rospkg.RosPack().get_path(PKG)
        cls.ring = CameraRing.load(os.path.join(cls.root, "config", "ring.yaml"))
        cls.tmp = tempfile.mkdtemp(prefix=f"identity_{cls.mode}_")
        cls.node = "/localizer" if cls.mode == "localization" else "/mapper"
        cls.diag: Dict[str, str] = {}
        rospy.Subscriber("/diagnostics", DiagnosticArray, cls._on_diag, queue_size=10)
        cls.holding = -1
        rospy.Subscriber(f"{RAW}/sim/at_waypoint", Int32, cls._on_waypoint, queue_size=10)
        cls.relaying = False
        # The relay opens and closes at ring-frame boundaries: a camera's detections pass on only
        # if their stamp is after the newest stamp seen before the opening and not after the newest
        # stamp passed on before the closing. Switching at one instant instead split the ring frame
        # in flight (some cameras' messages passed on, the others not): the node waited
        # input/timeout for the rest and assembled a frame the recording cannot reproduce.
        cls.lock = threading.Lock()
        cls.newest_seen = float("-inf")
        cls.newest_relayed = float("-inf")
        cls.open_after: Optional[float] = None
        cls.close_at: Optional[float] = None
        cls.newest_by_topic: Dict[str, float] = {}

    @classmethod
    def _on_diag(cls, msg):
        for s in msg.status:
            if s.name == "aruco_ring localizer: filter":
                cls.diag = {kv.key: kv.value for kv in s.values}

    @classmethod
    def _on_waypoint(cls, msg):
        cls.holding = max(cls.holding, int(msg.data))

    def _relayed(self) -> Dict[str, type]:
        """topic -> message type of what the simulator publishes and the node under test reads."""
        out: Dict[str, type] = {}
        for cam in self.ring.cameras:
            out[f"/{cam.namespace}/fiducial_vertices"] = FiducialArray
            out[f"/{cam.namespace}/camera_info"] = CameraInfo
        if self.mode == "localization":
            out.update({"/cmd_vel": Twist, "/odom": Odometry})
        return out

    def _start_relay(self):
        """(publishers, subscribers) of the relay, closed until ``self.relaying``."""
        pubs = {t: rospy.Publisher(t, typ, queue_size=100, latch=typ is CameraInfo) for t, typ in self._relayed().items()}

        def relay(msg, topic):
            if isinstance(msg, FiducialArray):
                stamp = msg.header.stamp.to_sec()
                with self.lock:
                    if self.open_after is None:
                        self.newest_seen = max(self.newest_seen, stamp)
                        return
                    if stamp <= self.open_after or (self.close_at is not None and stamp > self.close_at):
                        return
                    self.newest_relayed = max(self.newest_relayed, stamp)
                    self.newest_by_topic[topic] = max(self.newest_by_topic.get(topic, stamp), stamp)
                    pubs[topic].publish(msg)
            elif self.relaying:
                pubs[topic].publish(msg)
        # Deep queues: one read of rospy's takes every waiting message of a topic and keeps the newest
        # queue_size, so on a loaded machine a stalled relay thread with 20 lost a camera's message
        # and the node got that ring frame without it ("overtaken by a newer frame").
        subs = [rospy.Subscriber(RAW + t, typ, relay, callback_args=t, queue_size=1000)
                for t, typ in self._relayed().items()]
        return pubs, subs

    def _record_and_run(self, sim_args: List[str], run_until) -> str:
        """Start the simulator (relay closed), the recorder; open the relay once everyone is
        connected; run; close the relay; returns the bag path."""
        det = f"/{self.ring.cameras[0].namespace}/fiducial_vertices"
        _wait(f"{self.node} subscribed to {det}", lambda: self.node in _subscribers(det))
        pubs, subs = self._start_relay()
        bag = os.path.join(self.tmp, "run.bag")
        topics = sorted(set(self._relayed()) | {"/tf_static"} |
                        ({"/localizer/pose"} if self.mode == "localization" else set()))
        recorder = _Process(["rosbag", "record", "-O", bag, f"__name:={RECORDER}"] + topics,
                            os.path.join(self.tmp, "record.log"))
        sim = _Process(["roslaunch", PKG, "simulation.launch", "mode:=corners", f"rate:={RATE_HZ}",
                        f"__ns:={RAW.strip('/')}"] + sim_args, os.path.join(self.tmp, "simulator.log"))
        try:
            _wait("the recorder's subscriptions", lambda: all(f"/{RECORDER}" in _subscribers(t) for t in topics))
            # The node under test and the recorder connected to every relayed topic, the relay to
            # the simulator: from now on both get every message.
            _wait("the node's and the recorder's connections", lambda: all(p.get_num_connections() >= 2
                                                                           for p in pubs.values()))
            _wait("the simulator's topics", lambda: all(s.get_num_connections() >= 1 for s in subs))
            for cam in self.ring.cameras:
                pubs[f"/{cam.namespace}/camera_info"].publish(model_to_camera_info(cam.model, cam.frame_id))
            time.sleep(1.0)
            with self.lock:
                self.open_after = self.newest_seen
                self.relaying = True
            run_until()
        finally:
            with self.lock:
                self.close_at = self.newest_relayed
                self.relaying = False
            # Every camera's message of the last ring frame passed on (on a loaded machine some
            # were still in the relay's queues), then delivered:
            detection_topics = [t for t, typ in self._relayed().items() if typ is FiducialArray]
            def last_frame_out() -> bool:
                newest = self.newest_by_topic
                return all(newest.get(t, float("-inf")) >= self.close_at - 0.015 for t in detection_topics)
            end = time.monotonic() + 10.0
            while time.monotonic() < end and not last_frame_out():
                time.sleep(0.05)
            # The last relayed messages delivered, and the recording stops before the localizer's
            # predict-only output for silent cameras starts (the .test files set input/silent_after
            # to 5 s): that one follows the node's timer, which no bag records.
            time.sleep(0.6)
            recorder.stop()
            sim.stop()
            if self.mode == "mapping":
                self._save_map()
        return bag

    def _save_map(self) -> None:
        rospy.wait_for_service("/mapper/save_map", 30.0)
        res = rospy.ServiceProxy("/mapper/save_map", Trigger)()
        self.assertTrue(res.success, res.message)
        # A ring frame the mapper assembled without a camera (it waited input/timeout for it in
        # vain) is one the recording cannot reproduce: say so rather than compare.
        self.assertNotIn("without every camera", res.message, f"the mapper split ring frames: {res.message}")

    @staticmethod
    def _aruco_ring(args: List[str], log: str) -> None:
        with open(log, "w") as fh:
            rc = subprocess.call(["aruco_ring"] + args, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        if rc != 0:
            raise AssertionError(f"aruco_ring {' '.join(args)} exited {rc}:\n{open(log).read()[-3000:]}")

    def test_offline_equals_live(self):
        getattr(self, f"_check_{self.mode}")()

    # --- localization -----------------------------------------------------------------------------

    def _check_localization(self):
        def run_until():
            end = time.monotonic() + 30.0
            while time.monotonic() < end and not rospy.is_shutdown():
                time.sleep(0.2)
        bag = self._record_and_run(["waypoints:=test_positions", "hold_time:=1.0"], run_until)
        live = []
        with rosbag.Bag(bag) as b:
            for _, msg, _ in b.read_messages(topics=["/localizer/pose"]):
                T = pose_msg_to_transform(msg.pose.pose)
                live.append((msg.header.stamp.to_sec(), T[0, 3], T[1, 3], T[2, 3], geo.se2_from_transform(T)[2]))
        diag = dict(self.diag)
        self.assertGreater(len(live), 50, f"only {len(live)} live poses recorded; diagnostics {diag}")
        self.assertEqual(diag.get("dropped_stale"), "0", f"the localizer dropped frames: {diag}")
        self.assertEqual(diag.get("frames_with_missing_cameras"), "0", f"frames without every camera: {diag}")
        out_csv = os.path.join(self.tmp, "offline.csv")
        self._aruco_ring(["localize", bag, "--map", os.path.join(self.root, "test", "data", "lab_truth_map.yaml"),
                          "--out", os.path.join(self.tmp, "offline.tum"), "--csv", out_csv],
                         os.path.join(self.tmp, "localize.log"))
        offline = [(float(r["stamp"]), float(r["x"]), float(r["y"]), float(r["z"]), float(r["yaw"]))
                   for r in csv.DictReader(open(out_csv))]
        by_stamp = {round(r[0], 6): r for r in offline}
        worst = 0.0
        missing = []
        for t, x, y, z, yaw in live:
            o = by_stamp.get(round(t, 6))
            if o is None:
                missing.append(t)
                continue
            worst = max(worst, abs(o[1] - x), abs(o[2] - y), abs(o[3] - z), abs(geo.angle_diff(o[4], yaw)))
        self.assertFalse(missing, f"{len(missing)} live poses have no offline pose at their stamp (first "
                                  f"{missing[:5]}); diagnostics {diag}")
        t0, t1 = live[0][0], live[-1][0]
        extra = [o[0] for o in offline if t0 - 1e-6 <= o[0] <= t1 + 1e-6 and round(o[0], 6) not in
                 {round(r[0], 6) for r in live}]
        self.assertFalse(extra, f"offline poses the node did not publish: {extra[:5]}; diagnostics {diag}")
        self.assertLessEqual(worst, TOL, f"offline vs live: {worst:.3g} (m or rad) over {len(live)} poses")
        rospy.loginfo("identity: %d live poses equal offline to %.2g (m, rad)", len(live), worst)

    # --- mapping ----------------------------------------------------------------------------------

    def _check_mapping(self):
        node_map = rospy.get_param("/mapper/map_file")
        n_stations = 5

        def run_until():
            _wait("the simulator at its last mapping station", lambda: self.holding >= n_stations - 1, 120.0)
            time.sleep(2.0)
        bag = self._record_and_run(["waypoints:=mapping_stations", "drive:=teleport", "hold_time:=2.0"], run_until)
        out = os.path.join(self.tmp, "offline_map.yaml")
        self._aruco_ring(["build-map", bag, "--out", out], os.path.join(self.tmp, "build_map.log"))
        live, offline = MarkerMap.load(node_map), MarkerMap.load(out)
        self.assertEqual(sorted(live.ids), sorted(offline.ids))
        self.assertGreaterEqual(len(live), 8, f"only {len(live)} markers mapped")
        self.assertEqual(live.reference_marker, offline.reference_marker)
        worst = max(float(np.abs(live.T_map_marker(i) - offline.T_map_marker(i)).max()) for i in live.ids)
        self.assertLessEqual(worst, TOL, f"offline vs live map: largest difference {worst:.3g}")
        rospy.loginfo("identity: %d markers equal offline to %.2g", len(live), worst)


def main(argv: Optional[List[str]] = None) -> None:
    args = [a for a in (argv or sys.argv[1:]) if not a.startswith("__") and not a.startswith("--gtest")]
    IdentityTest.mode = args[0] if args else "localization"
    rostest.rosrun(PKG, f"identity_{IdentityTest.mode}", IdentityTest)


if __name__ == "__main__":
    main()
