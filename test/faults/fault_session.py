"""One fault-injection run against a live localizer (the test side of test/integration/faults_*.test).

The ``simulator`` node (corners mode, owning ``/clock``, in namespace ``lab``: its ring topics are
``lab/ring/camK/...``) plays the lab; a :class:`fault_relay.FaultRelay` in this process relays them
to ``ring/camK/...`` for the localizer with the message faults of the phase in force (by stamp);
this session:

* drives the robot along ``path(t)`` (t: seconds of the run) through the simulator's
  ``lab/cmd_vel`` (the body-frame velocity of the path at the true heading; open loop, so a
  kidnap offsets the rest of the run, as a real one would);
* triggers the simulator's hooks when a phase that names them starts: ``lab/sim/teleport`` (a
  kidnap by ``Phase.kidnap``) and ``lab/sim/time_jump`` (``Phase.time_jump``); the phase is then
  moved to start where the event really happened (seen in the ground truth);
* records the ground truth (``lab/sim/ground_truth``), the localizer's ``~pose`` (matched to the
  truth by stamp), ``/diagnostics`` and the localizer's ``/rosout`` lines.

Times ``t`` are seconds of the run: ``stamp - t0`` (``t0`` = the simulator's ``clock.start_time``),
with the clock's jump taken out.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import rospy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Pose2D, PoseStamped, PoseWithCovarianceStamped, Twist
from rosgraph_msgs.msg import Log
from std_msgs.msg import Float64

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import pose_msg_to_transform, stamp_to_sec  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

from fault_relay import FaultRelay  # noqa: E402
from faults import FaultSchedule, Phase  # noqa: E402

LAB = "lab"   # the simulator's namespace


@dataclass
class PoseRecord:
    """One ~pose message: stamp, the phase, run time t, (x, y, yaw), the truth, std x/y (m) and yaw (rad)."""

    stamp: float
    phase: str
    t: float
    pose: np.ndarray
    truth: Optional[np.ndarray]
    std_xy: float
    std_yaw: float

    @property
    def error(self) -> float:
        return float("nan") if self.truth is None else float(np.hypot(*(self.pose[:2] - self.truth[:2])))


@dataclass
class DiagRecord:
    t: float          # run time when received
    phase: str
    silent: List[str]  # cameras the diagnostics call not alive
    values: Dict[str, str]


def _key(stamp: float) -> int:
    return int(round(stamp * 1000))


class FaultSession:
    """See module docstring. ``t0``: the simulator's first stamp (its ``clock.start_time``)."""

    def __init__(self, path: Callable[[float], np.ndarray], schedule: FaultSchedule, ring_file: str,
                 t0: float, rate_hz: float, seed: int = 0, node: str = "/localizer"):
        self.path = path
        self.schedule = schedule
        self.t0 = float(t0)
        self.dt = 1.0 / float(rate_hz)
        self.node = node
        jumps = [p.time_jump for p in schedule.phases if p.time_jump]
        if len(jumps) > 1 or (jumps and -jumps[0] <= schedule.duration + 1.0):
            # Stamps after the jump must all lie before t0, so a stamp alone tells which side it is on.
            raise ValueError(f"at most one time jump, back by more than the run ({schedule.duration} s): {jumps}")
        self.jump = jumps[0] if jumps else 0.0
        scene = Scene.default()
        self.lock = threading.Lock()
        self.truth: Dict[int, np.ndarray] = {}
        self._poses: List[Tuple[float, np.ndarray, float, float]] = []
        self.diags: List[DiagRecord] = []
        self.logs: List[Tuple[float, int, str]] = []
        self.t_now = -1.0
        self._last_truth: Optional[np.ndarray] = None
        self._fired: Dict[str, float] = {}     # phase name -> run time its event was asked for
        self._events: Dict[str, float] = {}    # phase name -> run time its event happened
        self.relay = FaultRelay(CameraRing.load(ring_file), self.faults_at, in_ns=f"{LAB}",
                                mapped_ids=scene.marker_ids, sizes={m.marker_id: m.size for m in scene.markers},
                                seed=seed)
        self.cmd_pub = rospy.Publisher(f"{LAB}/cmd_vel", Twist, queue_size=5)
        self.teleport_pub = rospy.Publisher(f"{LAB}/sim/teleport", Pose2D, queue_size=2)
        self.jump_pub = rospy.Publisher(f"{LAB}/sim/time_jump", Float64, queue_size=2)
        rospy.Subscriber(f"{LAB}/sim/ground_truth", PoseStamped, self._on_truth, queue_size=100)
        rospy.Subscriber(f"{node}/pose", PoseWithCovarianceStamped, self._on_pose, queue_size=100)
        rospy.Subscriber("/diagnostics", DiagnosticArray, self._on_diag, queue_size=20)
        rospy.Subscriber("/rosout", Log, self._on_log, queue_size=200)

    # --- time -------------------------------------------------------------------------------------

    def run_time(self, stamp: float) -> float:
        """Seconds of the run of a message stamp (the clock's jump taken out)."""
        return stamp - self.t0 if stamp >= self.t0 - 1e-6 else stamp - self.t0 - self.jump

    def faults_at(self, stamp: float) -> Phase:
        return self.schedule.at(self.run_time(stamp))

    # --- recording, driving, events -----------------------------------------------------------------

    def _on_truth(self, msg: PoseStamped) -> None:
        stamp = stamp_to_sec(msg.header.stamp)
        t = self.run_time(stamp)
        truth = geo.se2_from_transform(pose_msg_to_transform(msg.pose))
        with self.lock:
            previous, self._last_truth = self._last_truth, truth
            self.truth[_key(stamp)] = truth
            self.t_now = max(self.t_now, t)
            for name in list(self._fired):
                if name in self._events:
                    continue
                p = self.schedule.phase(name)
                jumped = p.time_jump and stamp < self.t0
                moved = p.kidnap is not None and previous is not None and np.hypot(*(truth[:2] - previous[:2])) > 0.5
                if jumped or moved:
                    self._events[name] = t
        # Drive along the path: its velocity at t, in the robot frame at the true heading.
        a, b = np.asarray(self.path(t - 0.5 * self.dt)), np.asarray(self.path(t + 0.5 * self.dt))
        v = (b[:2] - a[:2]) / self.dt
        c, s = np.cos(truth[2]), np.sin(truth[2])
        cmd = Twist()
        cmd.linear.x, cmd.linear.y = c * v[0] + s * v[1], -s * v[0] + c * v[1]
        cmd.angular.z = float(geo.angle_diff(b[2], a[2]) / self.dt)
        self.cmd_pub.publish(cmd)
        # Ask for the events of the next frame's phase now, so they happen at that frame.
        nxt = self.schedule.at(t + self.dt)
        if nxt.name not in self._fired and (nxt.kidnap is not None or nxt.time_jump) and \
                t + self.dt >= nxt.start - 1e-6:
            self._fired[nxt.name] = t
            if nxt.kidnap is not None:
                dx, dy, dyaw = nxt.kidnap
                self.teleport_pub.publish(Pose2D(x=truth[0] + dx, y=truth[1] + dy, theta=geo.wrap_angle(truth[2] + dyaw)))
            if nxt.time_jump:
                self.jump_pub.publish(Float64(data=nxt.time_jump))

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        p = msg.pose.pose
        cov = msg.pose.covariance
        with self.lock:
            self._poses.append((stamp_to_sec(msg.header.stamp),
                                geo.se2_from_transform(pose_msg_to_transform(p)),
                                float(np.sqrt(max(cov[0], cov[7]))), float(np.sqrt(cov[35]))))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        silent, values = [], {}
        for s in msg.status:
            if "camera" in s.name and s.hardware_id:
                kv = {v.key: v.value for v in s.values}
                if kv.get("alive") == "False":
                    silent.append(s.hardware_id)
            elif "filter" in s.name:
                values = {v.key: v.value for v in s.values}
                values["_message"] = s.message
                values["_level"] = str(s.level)
        if not values and not silent:
            return
        with self.lock:
            self.diags.append(DiagRecord(self.t_now, self.schedule.at(self.t_now).name, sorted(silent), values))

    def _on_log(self, msg: Log) -> None:
        if msg.name.rstrip("/").endswith(self.node.strip("/")):
            with self.lock:
                self.logs.append((self.t_now, int(msg.level), msg.msg))

    # --- the run ------------------------------------------------------------------------------------

    def wait_connected(self, timeout: float = 60.0) -> bool:
        """Until the simulator's ring topics reach the relay and the localizer listens to it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not rospy.is_shutdown():
            if self.relay.connected():
                return True
            time.sleep(0.1)
        return False

    def run(self, timeout: float = 300.0) -> None:
        """Until the schedule's end in run time (the simulator paces itself in wall time); then the
        phases whose event happened later than asked for start where it did."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not rospy.is_shutdown():
            with self.lock:
                if self.t_now >= self.schedule.duration:
                    break
            time.sleep(0.05)
        else:
            raise RuntimeError(f"the run reached t={self.t_now:.1f} s of {self.schedule.duration} s in {timeout} s")
        with self.lock:
            missing = sorted(set(self._fired) - set(self._events))
            events = dict(self._events)
        if missing:
            raise RuntimeError(f"events asked for but not seen in the ground truth: {missing}")
        for name, t in events.items():
            self.schedule.move_start(name, round(t, 6))

    # --- queries ------------------------------------------------------------------------------------

    @property
    def poses(self) -> List[PoseRecord]:
        """Every pose so far, with its truth (same stamp), phase and run time."""
        with self.lock:
            raw, truth = list(self._poses), dict(self.truth)
        out = []
        for stamp, pose, std_xy, std_yaw in raw:
            t = self.run_time(stamp)
            out.append(PoseRecord(stamp, self.schedule.at(t).name, t, pose, truth.get(_key(stamp)), std_xy, std_yaw))
        return out

    @property
    def injected(self) -> Dict[str, int]:
        return dict(self.relay.injected)

    def poses_in(self, phase: str, after: float = 0.0) -> List[PoseRecord]:
        """Poses of a phase whose stamp lies at least ``after`` s into it (and before its end: the
        simulator goes on after the run, the schedule does not)."""
        p = self.schedule.phase(phase)
        return [r for r in self.poses if r.phase == phase and p.start + after <= r.t < p.end]

    def diags_in(self, phase: str, after: float = 0.0) -> List[DiagRecord]:
        p = self.schedule.phase(phase)
        with self.lock:
            return [d for d in self.diags if p.start + after <= d.t < p.end]

    def summary(self) -> Dict[str, object]:
        """Per phase: poses, max/median position error (cm), std x/y at start and end (m); injected faults."""
        out: Dict[str, object] = {"injected": self.injected, "phases": {}}
        for ph in self.schedule.phases:
            poses = self.poses_in(ph.name)
            errs = [r.error for r in poses if np.isfinite(r.error)]
            diags = self.diags_in(ph.name)
            out["phases"][ph.name] = {  # type: ignore[index]
                "start_s": round(ph.start, 3), "duration_s": round(ph.duration, 3), "poses": len(poses),
                "max_err_cm": round(100 * max(errs), 2) if errs else None,
                "median_err_cm": round(100 * float(np.median(errs)), 2) if errs else None,
                "std_xy_first_m": round(poses[0].std_xy, 4) if poses else None,
                "std_xy_last_m": round(poses[-1].std_xy, 4) if poses else None,
                "silent_in_diagnostics": diags[-1].silent if diags else None}
        if self.diags:
            out["last_filter_diagnostics"] = self.diags[-1].values
        return out

    def write_summary(self, path: str, extra: Optional[Dict[str, object]] = None) -> None:
        data = self.summary()
        data.update(extra or {})
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as handle:
            json.dump(data, handle, indent=1, default=str)
