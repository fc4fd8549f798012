"""The test side of the hostile-input rostests (test/integration/hostile_*.test, issue 14).

The stock ``localization.launch sim:=true map_file:=test/data/lab_truth_map.yaml`` runs in wall
time: the simulator drives the paper's test positions (cmd_vel, at most ``robot/limits/max_speed``),
publishes the ring's detections, ``odom`` and ``sim/ground_truth``; the localizer localizes on the
true map. A :class:`HostileSession` in the test node records, from before the first fault:

* every ``/localizer/pose`` with its receive time, matched to ``sim/ground_truth`` by stamp;
* the localizer's ``/rosout`` lines (to count the warnings of each fault);
* a tf listener (what rviz or move_base would have): after a fault it must still resolve
  ``map -> base_link`` at ``now``.

and gives each fault a window (:meth:`window`) in which the checks are made: the position error
against the truth, the step between consecutive poses against what the robot can move, and
the time to recover. Times are ROS time (= wall time here), s.
"""
from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
import rosgraph
import rospy
import tf2_ros
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rosgraph_msgs.msg import Log

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.ros.conversions import pose_msg_to_transform, stamp_to_sec

#: Position error a pose may have (issue 14: "no pose more than 10 cm off the ground truth").
MAX_ERROR_M = 0.10
#: Measurement noise a step between two poses may add to the robot's own motion, m. With the fixes,
#: every window of these tests gave steps at most 0.3 cm beyond the true motion between the two
#: stamps (0.3 px corner noise, a miscalibrated rig, load 8-15); 3 cm is ten times that and under a
#: third of MAX_ERROR_M (without the fixes the flood gave 5.7 cm).
STEP_NOISE_M = 0.03
#: The throttle period of the package's warnings (throttle.WARN_PERIOD), s.
WARN_PERIOD = 5.0


@dataclass
class Pose:
    received: float       # ROS time when it arrived
    stamp: float
    se2: np.ndarray       # (x, y, yaw) in the map frame
    std_xy: float
    truth: Optional[np.ndarray]

    @property
    def error(self) -> float:
        return math.nan if self.truth is None else float(np.hypot(*(self.se2[:2] - self.truth[:2])))


class HostileSession:
    """Recording and checks for one hostile rostest (module docstring)."""

    def __init__(self, node: str = "/localizer", map_frame: str = "map", base_frame: str = "base_link"):
        self.node = node
        self.map_frame, self.base_frame = map_frame, base_frame
        self.lock = threading.Lock()
        self._truth: Dict[int, np.ndarray] = {}
        self._poses: List[Tuple[float, float, np.ndarray, float]] = []
        self.logs: List[Tuple[float, int, str]] = []
        self.tf = tf2_ros.Buffer(cache_time=rospy.Duration(30.0))
        self._tf_listener = tf2_ros.TransformListener(self.tf)
        rospy.Subscriber("sim/ground_truth", PoseStamped, self._on_truth, queue_size=50)
        rospy.Subscriber(f"{node}/pose", PoseWithCovarianceStamped, self._on_pose, queue_size=50)
        rospy.Subscriber("/rosout", Log, self._on_log, queue_size=500)
        self.max_speed = float(rospy.get_param("/simulator/robot/limits/max_speed"))

    # --- recording ----------------------------------------------------------------------------

    @staticmethod
    def _key(stamp: float) -> int:
        return int(round(stamp * 1000.0))

    def _on_truth(self, msg: PoseStamped) -> None:
        se2 = geo.se2_from_transform(pose_msg_to_transform(msg.pose))
        with self.lock:
            self._truth[self._key(stamp_to_sec(msg.header.stamp))] = se2

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        now = rospy.get_time()
        cov = msg.pose.covariance
        with self.lock:
            self._poses.append((now, stamp_to_sec(msg.header.stamp),
                                geo.se2_from_transform(pose_msg_to_transform(msg.pose.pose)),
                                float(np.sqrt(max(cov[0], cov[7])))))

    def _on_log(self, msg: Log) -> None:
        if msg.name.rstrip("/") == self.node.rstrip("/"):
            with self.lock:
                self.logs.append((rospy.get_time(), int(msg.level), msg.msg))

    # --- queries ------------------------------------------------------------------------------

    def poses(self, t0: float = -math.inf, t1: float = math.inf) -> List[Pose]:
        """Poses stamped in [t0, t1), with their truth: the simulator's at the same stamp (a ring
        frame's), else interpolated between its two frames around the stamp (a prediction's)."""
        with self.lock:
            raw, truth = list(self._poses), dict(self._truth)
        keys = np.array(sorted(truth))
        return [Pose(r, s, p, sd, self._truth_at(s, truth, keys)) for r, s, p, sd in raw if t0 <= s < t1]

    def _truth_at(self, stamp: float, truth: Dict[int, np.ndarray], keys: np.ndarray) -> Optional[np.ndarray]:
        k = self._key(stamp)
        if k in truth:
            return truth[k]
        i = int(np.searchsorted(keys, k))
        if i == 0 or i == len(keys) or keys[i] - keys[i - 1] > 150:   # frames are 100 ms apart
            return None
        a, b = truth[int(keys[i - 1])], truth[int(keys[i])]
        w = (k - keys[i - 1]) / float(keys[i] - keys[i - 1])
        return np.array([a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), a[2] + w * geo.angle_diff(b[2], a[2])])

    def frames(self, t0: float = -math.inf, t1: float = math.inf) -> int:
        """Ring frames the simulator made with stamps in [t0, t1) (one ``sim/ground_truth`` each)."""
        with self.lock:
            return sum(1 for k in self._truth if t0 <= k / 1000.0 < t1)

    def posed_fraction(self, t0: float, t1: float) -> float:
        """Of the simulator's ring frames stamped in [t0, t1), the fraction the localizer published a
        pose for (at the frame's stamp): what the localizer did with the frames it was given,
        whatever pace the simulator kept on a loaded machine."""
        with self.lock:
            truth = {k for k in self._truth if t0 <= k / 1000.0 < t1}
            posed = {self._key(s) for _, s, _, _ in self._poses} & truth
        return len(posed) / len(truth) if truth else math.nan

    def worst(self, t0: float, t1: float) -> Pose:
        """The pose with the largest error in [t0, t1) (those with a truth)."""
        poses = [p for p in self.poses(t0, t1) if p.truth is not None]
        assert poses, f"no pose with a ground truth between {t0:.1f} and {t1:.1f} s"
        return max(poses, key=lambda p: p.error)

    def worst_step(self, t0: float, t1: float) -> Tuple[float, Pose, Pose]:
        """The largest excess of a step between consecutive poses over the robot's true motion
        between their stamps (m), and the two poses. Measured against the truth's own step, since
        the robot's true motion can be anything up to max_speed x dt."""
        poses = [p for p in self.poses(t0, t1) if p.truth is not None]
        worst = (0.0, None, None)
        for a, b in zip(poses, poses[1:]):
            step = float(np.hypot(*(b.se2[:2] - a.se2[:2])))
            allowed = float(np.hypot(*(b.truth[:2] - a.truth[:2])))
            if step - allowed > worst[0]:
                worst = (step - allowed, a, b)
        return worst  # type: ignore[return-value]

    def check_windows(self, windows: Dict[str, Tuple[float, float]]) -> None:
        """The checks of every hostile rostest, per window: no pose more than MAX_ERROR_M off the
        truth, no step more than STEP_NOISE_M beyond the robot's motion (AssertionError naming it)."""
        for name, (t0, t1) in windows.items():
            worst = self.worst(t0, t1)
            assert worst.error < MAX_ERROR_M, (f"{name}: {100 * worst.error:.1f} cm off at {worst.stamp:.2f} "
                                               f"({self.summary(t0, t1)})")
            excess, a, b = self.worst_step(t0, t1)
            assert excess < STEP_NOISE_M, (f"{name}: a step {100 * excess:.1f} cm beyond the robot's motion between "
                                           f"{getattr(a, 'stamp', 0):.2f} and {getattr(b, 'stamp', 0):.2f}")

    def recovered_at(self, t0: float, t1: float, tol: float = MAX_ERROR_M) -> Optional[float]:
        """The first stamp in [t0, t1) from which every pose is within ``tol`` of the truth."""
        poses = [p for p in self.poses(t0, t1) if p.truth is not None]
        for i, p in enumerate(poses):
            if all(q.error < tol for q in poses[i:]):
                return p.stamp
        return None

    def lines(self, needle: str, t0: float = -math.inf, t1: float = math.inf) -> List[str]:
        with self.lock:
            return [m for t, _, m in self.logs if t0 <= t < t1 and needle in m]

    def max_throttled_lines(self, seconds: float) -> int:
        """Lines one throttled problem may give over ``seconds``: one per period, plus the first."""
        return int(seconds // WARN_PERIOD) + 1

    def lookup_now(self, timeout: float = 1.0):
        """``map -> base_link`` at now through the listener started before the faults (raises)."""
        return self.tf.lookup_transform(self.map_frame, self.base_frame, rospy.Time.now(), rospy.Duration(timeout))

    # --- driving the run ------------------------------------------------------------------------

    def wait_tracking(self, timeout: float = 90.0, settle: float = 3.0) -> float:
        """Until the localizer has published poses within MAX_ERROR_M / 2 for ``settle`` s; returns now."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not rospy.is_shutdown():
            now = rospy.get_time()
            recent = [p for p in self.poses(now - settle) if p.truth is not None]
            if len(recent) >= 5 * settle and max(p.error for p in recent) < MAX_ERROR_M / 2 and \
                    now - recent[0].stamp >= settle - 0.5:
                return now
            time.sleep(0.2)
        raise AssertionError(f"the localizer did not track within {timeout} s ({len(self.poses())} poses)")

    def wait_driving(self, speed: float = 0.15, timeout: float = 30.0) -> None:
        """Until the true robot drives faster than ``speed`` (m/s; the simulator holds each test
        position 3 s and drives between them)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not rospy.is_shutdown():
            with self.lock:
                recent = sorted(self._truth.items())[-6:]
            if len(recent) == 6:
                (k0, a), (k1, b) = recent[0], recent[-1]
                if np.hypot(*(b[:2] - a[:2])) / max(1e-3 * (k1 - k0), 1e-3) > speed:
                    return
            time.sleep(0.05)
        raise AssertionError(f"the simulated robot did not drive faster than {speed} m/s within {timeout} s")

    @staticmethod
    def sleep(seconds: float) -> None:
        rospy.rostime.wallsleep(seconds)

    def pid_of(self, node: str) -> int:
        """The process id of a node (its XML-RPC getPid)."""
        from xmlrpc.client import ServerProxy

        uri = rosgraph.Master("/hostile").lookupNode(node)
        code, _, pid = ServerProxy(uri).getPid("/hostile")
        assert code == 1, f"getPid of {node} failed"
        return int(pid)

    def figures(self, t0: float, t1: float) -> Dict[str, object]:
        """Figures of one window, for results/hostile/*.json and docs/reliability.md."""
        poses = [p for p in self.poses(t0, t1) if p.truth is not None]
        errs = np.array([p.error for p in poses]) if poses else np.array([math.nan])
        return {"seconds": round(t1 - t0, 2), "poses": len(poses), "err_cm_median": round(100 * float(np.median(errs)), 2),
                "err_cm_max": round(100 * float(np.max(errs)), 2),
                "step_excess_cm_max": round(100 * self.worst_step(t0, t1)[0], 2)}

    def write_results(self, name: str, windows: Dict[str, Tuple[float, float]], extra: Optional[dict] = None) -> str:
        """results/hostile/<name>.json: the figures of every window (+ ``extra``); returns the path."""
        root = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
        path = os.path.join(root, "results", "hostile", f"{name}.json")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        out = {k: self.figures(*w) for k, w in windows.items()}
        out.update(extra or {})
        out["load_average"] = os.getloadavg()[0]
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(out, fh, indent=2)
        return path

    def summary(self, t0: float, t1: float) -> str:
        poses = [p for p in self.poses(t0, t1) if p.truth is not None]
        if not poses:
            return "no poses"
        errs = np.array([p.error for p in poses])
        return (f"{len(poses)} poses, error median {100 * np.median(errs):.2f} cm, max {100 * errs.max():.2f} cm, "
                f"step excess max {100 * self.worst_step(t0, t1)[0]:.2f} cm")
