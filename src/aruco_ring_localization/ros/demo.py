"""``make demo``: the paper's experiment (§III) end to end on the simulated lab, with the real ROS nodes.

``python -m aruco_ring_localization.ros.demo [--fusion joint|paper] [--method refined|paper]
[--mode corners|images] [--gui] [--out results/demo]``

1. starts its own roscore (a free port, so it never disturbs a running ROS);
2. mapping: ``launch/demo.launch phase:=mapping``: the ``simulator`` node (simulation.launch, its
   parameters in ``--out``/simulator_mapping.yaml; in ``--mode images`` with the 8 detector nodes)
   holds the robot at the plate centre (the paper's single placement) while mapping.launch's
   mapper collects ``--mapping-frames`` frames; then ``/mapper/save_map`` writes the map;
3. localization: ``demo.launch phase:=localization``: the simulator (simulator_localization.yaml)
   drives the route - the mapping pose, then the paper's 15 positions and 8 orientations, each
   held ``--hold-frames`` frames - in lockstep with localization.launch's localizer on the saved
   map, and the comparison node runs beside it; this process records ``sim/ground_truth`` and
   ``localizer/pose`` by stamp; the frames where the true robot rests at a stop are that stop's;
4. report: Table I (x, y, Euclidean error per position, cm), Table II (yaw error per
   orientation, deg), the map error, a one-line summary; under ``--out``: ``summary.json``,
   ``table1.md``/``.csv``, ``table2.md``/``.csv``, ``trajectory_estimate.tum``,
   ``trajectory_truth.tum``, ``map.yaml`` and the figures (``map.png``, ``fig8_positions.png``,
   ``fig9_camera_estimates.png``, ``fig10_orientations.png``).

The comparison is fair: the truth is expressed in the map frame through the TRUE pose of the
map's reference marker and the map's own frame definition
(:func:`evaluation.truth_in_map_frame`); nothing is fitted that could hide an error.

The simulator runs in lockstep with the localizer (``lockstep.topics: [localizer/pose]``: each
frame waits for the pose it produces, up to a timeout), so the result does not depend on the
machine's speed, only the run time does. This process only orchestrates (processes, the save
service, recording); the lab is the simulator node's and the report is pure.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .. import geometry as geo
from .. import trajectory as tr
from ..config import to_dict, with_overrides
from ..errors import ArucoRingError
from ..fileio import atomic_write_text
from ..marker_map import MarkerMap
from ..simulation.params import SimulatorConfig
from ..simulation.scene import Scene

logger = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[3]
PACKAGE = "aruco_ring_localization"


# --------------------------------------------------------------------------------------------
# Plan and report (pure: no ROS; unit-tested)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StopPlan:
    """One stop of the drive: ``kind`` "position" (Table I) or "orientation" (Table II)."""

    kind: str
    label: str
    pose: Tuple[float, float, float]  # world frame, x m, y m, yaw rad


def plan_stops(test_positions: Sequence[Sequence[float]], test_orientations: Sequence[Sequence[float]]) -> List[StopPlan]:
    """The paper's stops: the positions (labels 1..N) in a serpentine order, then the orientations.

    Positions are visited row by row (rows = equal y within 5 cm), alternating the direction
    along x, so the robot never crosses the plate empty-handed; labels keep the scene's order.
    """
    pos = [StopPlan("position", str(k + 1), tuple(float(v) for v in p)) for k, p in enumerate(test_positions)]
    rows: List[List[StopPlan]] = []
    for stop in sorted(pos, key=lambda s: (s.pose[1], s.pose[0])):
        if rows and abs(rows[-1][0].pose[1] - stop.pose[1]) <= 0.05:
            rows[-1].append(stop)
        else:
            rows.append([stop])
    ordered = [s for k, row in enumerate(rows) for s in (row if k % 2 == 0 else row[::-1])]
    return ordered + [StopPlan("orientation", str(k + 1), tuple(float(v) for v in p))
                      for k, p in enumerate(test_orientations)]


def interpolate_motion(start: Sequence[float], goal: Sequence[float], dt: float, max_speed: float = 0.5,
                       max_yaw_rate: float = 0.6) -> List[Tuple[np.ndarray, np.ndarray]]:
    """Poses (and body-frame velocity commands) from ``start`` to ``goal``, one per ``dt`` s.

    Straight line and shortest rotation together, at constant speed limited by ``max_speed``
    (m/s) and ``max_yaw_rate`` (rad/s). Returns [(pose (x, y, yaw), cmd (vx, vy, wz) in the
    robot frame)], the last pose being ``goal``; empty when start == goal.
    """
    a = np.asarray(start, dtype=float)
    b = np.asarray(goal, dtype=float)
    dist = float(np.hypot(*(b[:2] - a[:2])))
    dyaw = float(geo.angle_diff(b[2], a[2]))
    duration = max(dist / max_speed, abs(dyaw) / max_yaw_rate)
    n = int(np.ceil(duration / dt - 1e-9))
    if n <= 0:
        return []
    v_world = (b[:2] - a[:2]) / (n * dt)
    w = dyaw / (n * dt)
    out = []
    for k in range(1, n + 1):
        f = k / n
        pose = np.array([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), geo.wrap_angle(a[2] + f * dyaw)])
        c, s = np.cos(pose[2]), np.sin(pose[2])
        cmd = np.array([c * v_world[0] + s * v_world[1], -s * v_world[0] + c * v_world[1], w])
        out.append((pose, cmd))
    return out


@dataclass
class StopRecord:
    """What the demo saw at one stop: the truth and our estimates (map frame)."""

    plan: StopPlan
    truth_world: np.ndarray                      # (3,) world frame
    estimates: List[Tuple[float, np.ndarray]] = field(default_factory=list)   # (stamp, (x, y, yaw) map)
    camera_estimates: List[np.ndarray] = field(default_factory=list)           # (K, 3) map, last frame


def se2_in_frame(T_frame_world: np.ndarray, pose_world: Sequence[float]) -> np.ndarray:
    """(x, y, yaw) of a world-frame planar pose expressed in another frame (4x4 ``T_frame_world``)."""
    return geo.se2_from_transform(T_frame_world @ geo.transform_from_se2(*pose_world))


def stop_rows(records: Sequence[StopRecord], T_map_world: np.ndarray, kind: str, use_last: int = 5) -> List[tr.StopError]:
    """Table rows of the stops of ``kind``: truth in the map frame vs the median of the last estimates."""
    rows = []
    for rec in sorted(records, key=lambda r: (int(r.plan.label) if r.plan.label.isdigit() else 0, r.plan.label)):
        if rec.plan.kind != kind:
            continue
        truth = se2_in_frame(T_map_world, rec.truth_world)
        if not rec.estimates:
            logger.warning("stop %s %s: no estimate recorded", kind, rec.plan.label)
            rows.append(tr.StopError(rec.plan.label, truth, np.full(3, np.nan), 0))
            continue
        est = np.array([e for _, e in rec.estimates[-use_last:]])
        fused = np.array([float(np.median(est[:, 0])), float(np.median(est[:, 1])), geo.circular_mean(est[:, 2])])
        stamps = [s for s, _ in rec.estimates[-use_last:]]
        rows.append(tr.StopError(rec.plan.label, truth, fused, len(est), float(stamps[0]), float(stamps[-1])))
    return rows


def summary_dict(pos_rows: Sequence[tr.StopError], yaw_rows: Sequence[tr.StopError], map_err: Optional[Dict[str, Any]],
                 fusion: str, method: str, mode: str, runtime_s: float) -> Dict[str, Any]:
    """The keys of ``summary.json`` (issue 6): position_error_cm, yaw_error_deg, map_error_mm, ..."""
    def cm(r):
        return float(100 * r.errors[2]) if np.all(np.isfinite(r.est)) else None

    def deg(r):
        return float(np.degrees(r.errors[3])) if np.all(np.isfinite(r.est)) else None

    pos = [cm(r) for r in pos_rows]
    yaw = [deg(r) for r in yaw_rows]
    pos_ok = np.array([p for p in pos if p is not None])
    yaw_ok = np.abs(np.array([y for y in yaw if y is not None]))
    out: Dict[str, Any] = {
        "position_error_cm": {
            "median": float(np.median(pos_ok)) if pos_ok.size else None,
            "max": float(np.max(pos_ok)) if pos_ok.size else None,
            "mean": float(np.mean(pos_ok)) if pos_ok.size else None,
            "per_position": {r.label: {"x": float(100 * r.errors[0]), "y": float(100 * r.errors[1]), "euclidean": p}
                             if p is not None else None for r, p in zip(pos_rows, pos)},
            "missing": len(pos) - int(pos_ok.size),
        },
        "yaw_error_deg": {
            "mean_abs": float(np.mean(yaw_ok)) if yaw_ok.size else None,
            "max_abs": float(np.max(yaw_ok)) if yaw_ok.size else None,
            "per_orientation": {r.label: y for r, y in zip(yaw_rows, yaw)},
            "missing": len(yaw) - int(yaw_ok.size),
        },
        "map_error_mm": None if map_err is None else {
            "rms": map_err["position_rms_mm"], "max": map_err["position_max_mm"],
            "rotation_mean_deg": map_err["rotation_mean_deg"], "rotation_max_deg": map_err["rotation_max_deg"],
            "markers": map_err["n"], "missing": map_err["missing"]},
        "fusion": fusion,
        "map_method": method,
        "mode": mode,
        "runtime_s": float(runtime_s),
        "paper": {"position_error_cm": {"median": 3.10, "max": 17.27}, "yaw_error_deg": {"mean_abs": 1.901, "max_abs": 4.501},
                  "reference": "gmapping"},
        "targets": {"position_error_cm": {"median": 1.0, "max": 3.0}, "yaw_error_deg": {"mean_abs": 0.3, "max_abs": 1.0}},
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "python": platform.python_version()},
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    return out


def consistency(rows: Sequence[tr.StopError]) -> Optional[Dict[str, Any]]:
    """Errors after the best-fit SE(2) alignment of all stop estimates onto the truth.

    NOT the headline: a fitted alignment absorbs how well the map frame is fixed (the reference
    marker's pose). It shows the localization's internal consistency, and with the headline
    numbers how much of the error is the map frame's.
    """
    if len(rows) < 3:
        return None
    est = np.array([r.est for r in rows])
    ref = np.array([r.ref for r in rows])
    T = tr.align_se2(est, ref)
    e = tr.pose_errors(ref, tr.apply_se2(T, est))
    d, y = 100 * e[:, 2], np.degrees(np.abs(e[:, 3]))
    return {"alignment": {"x_m": float(T[0]), "y_m": float(T[1]), "yaw_deg": float(np.degrees(T[2]))},
            "position_error_cm": {"median": float(np.median(d)), "max": float(np.max(d))},
            "yaw_error_deg": {"mean_abs": float(np.mean(y)), "max_abs": float(np.max(y))},
            "note": "after a fitted SE(2) alignment of all stops: internal consistency, not the accuracy"}


def summary_line(summary: Dict[str, Any]) -> str:
    """One line: the demo's numbers beside the paper's."""
    p, y, m = summary["position_error_cm"], summary["yaw_error_deg"], summary["map_error_mm"]

    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    line = (f"position error median {f(p['median'], '.2f')} cm, max {f(p['max'], '.2f')} cm; "
            f"|yaw| mean {f(y['mean_abs'], '.3f')} deg, max {f(y['max_abs'], '.3f')} deg")
    if m is not None:
        line += f"; map RMS {m['rms']:.1f} mm"
    line += (f" ({summary['fusion']} fusion, {summary['map_method']} map, {summary['mode']} mode, "
             f"{summary['runtime_s']:.0f} s)  [paper vs gmapping: 3.10 / 17.27 cm, 1.90 / 4.50 deg]")
    return line


def write_report(out_dir: Path, records: Sequence[StopRecord], est_map: MarkerMap, truth_map: MarkerMap, scene,
                 trajectory_est: Sequence[Tuple[float, np.ndarray]], trajectory_truth: Sequence[Tuple[float, np.ndarray]],
                 fusion: str, method: str, mode: str, runtime_s: float,
                 fig9_labels: Sequence[str] = ("1", "8", "15")) -> Dict[str, Any]:
    """Tables, summary.json, TUM trajectories and figures; returns the summary dict.

    The truth (world frame) goes into the map frame through ``T_map_world`` from the map's own
    frame definition applied to the true reference marker (no fitted alignment).
    """
    from .. import evaluation, plots
    from ..fileio import atomic_write_text

    out_dir.mkdir(parents=True, exist_ok=True)
    T_world_map = evaluation.truth_in_map_frame(est_map, truth_map)
    T_map_world = geo.inverse(T_world_map)
    pos_rows = stop_rows(records, T_map_world, "position")
    yaw_rows = stop_rows(records, T_map_world, "orientation")
    try:
        map_err = evaluation.map_error(est_map, truth_map)
    except ArucoRingError as exc:
        logger.warning("map error not computed: %s", exc)
        map_err = None
    ok_pos = [r for r in pos_rows if np.all(np.isfinite(r.est))]
    ok_yaw = [r for r in yaw_rows if np.all(np.isfinite(r.est))]
    t1 = tr.position_table_markdown(ok_pos, title="Table I. Errors in position (simulated lab)",
                                    reference_name="ground truth")
    t2 = tr.orientation_table_markdown(ok_yaw, title="Table II. Errors in orientation (simulated lab)",
                                       reference_name="ground truth")
    atomic_write_text(str(out_dir / "table1.md"), t1, keep_backup=False)
    atomic_write_text(str(out_dir / "table2.md"), t2, keep_backup=False)
    atomic_write_text(str(out_dir / "table1.csv"), tr.stops_csv(ok_pos), keep_backup=False)
    atomic_write_text(str(out_dir / "table2.csv"), tr.stops_csv(ok_yaw), keep_backup=False)
    summary = summary_dict(pos_rows, yaw_rows, map_err, fusion, method, mode, runtime_s)
    summary["after_best_fit_se2"] = consistency(ok_pos + ok_yaw)
    atomic_write_text(str(out_dir / "summary.json"), json.dumps(summary, indent=2) + "\n", keep_backup=False)
    if trajectory_est:
        tr.write_tum(str(out_dir / "trajectory_estimate.tum"),
                     tr.Trajectory.from_se2([s for s, _ in trajectory_est], np.array([p for _, p in trajectory_est])),
                     header=f"aruco_ring_localization demo: localizer ~pose in the marker map frame ({fusion} fusion)")
    if trajectory_truth:
        tr.write_tum(str(out_dir / "trajectory_truth.tum"),
                     tr.Trajectory.from_se2([s for s, _ in trajectory_truth],
                                            np.array([se2_in_frame(T_map_world, p) for _, p in trajectory_truth])),
                     header="aruco_ring_localization demo: ground truth in the marker map frame")
    # Figures in the scene's world frame (the room is axis-aligned there): the estimates go there
    # through the same T_world_map (no fit), so every error is the one of the tables.
    def world(p):
        return se2_in_frame(T_world_map, p)

    plate = plots.plate_polygon(scene.plate.centre, scene.plate.size)
    room = plots.room_polygon(scene.room.origin, scene.room.size)
    est_world = {e.marker_id: geo.transform_points(T_world_map, est_map.corners(e.marker_id)) for e in est_map}
    truth_corners = {e.marker_id: truth_map.corners(e.marker_id) for e in truth_map}
    plots.plot_map(str(out_dir / "map.png"), est_world, truth_corners, plate=plate, room=room,
                   robot_pose=tuple(scene.mapping_pose), footprint=tuple(scene.robot.footprint),
                   title=f"Marker map ({method}, reference marker {est_map.reference_marker}) in the lab, "
                         f"RMS {map_err['position_rms_mm']:.1f} mm" if map_err else f"Marker map ({method})")
    if ok_pos:
        plots.plot_positions(str(out_dir / "fig8_positions.png"), np.array([world(r.ref)[:2] for r in ok_pos]),
                             np.array([world(r.est)[:2] for r in ok_pos]), plate=plate, labels=[r.label for r in ok_pos],
                             errors_cm=[100 * r.errors[2] for r in ok_pos],
                             title="15 positions: ground truth and estimated (Fig. 8)")
    cases = []
    for rec in records:
        if rec.plan.kind == "position" and rec.plan.label in fig9_labels and rec.estimates:
            row = next((r for r in pos_rows if r.label == rec.plan.label), None)
            if row is None or not np.all(np.isfinite(row.est)):
                continue
            cams = {f"c{k}": world(p) for k, p in enumerate(rec.camera_estimates)}
            cases.append({"label": f"position {rec.plan.label}", "true": world(row.ref), "fused": world(row.est),
                          "cameras": cams})
    if cases:
        plots.plot_camera_estimates(str(out_dir / "fig9_camera_estimates.png"), cases)
    if ok_yaw:
        plots.plot_orientations(str(out_dir / "fig10_orientations.png"), [world(r.ref)[2] for r in ok_yaw],
                                [world(r.est)[2] for r in ok_yaw], labels=[r.label for r in ok_yaw])
    return summary


# --------------------------------------------------------------------------------------------
# Processes (roscore, roslaunch) owned by the demo
# --------------------------------------------------------------------------------------------
class Progress:
    """Progress lines on stdout with the elapsed time."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self._last_inline = False

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def __call__(self, text: str, inline: bool = False) -> None:
        line = f"[demo {self.elapsed():6.1f} s] {text}"
        if inline and sys.stdout.isatty():
            sys.stdout.write("\r" + line.ljust(100))
            self._last_inline = True
        else:
            if self._last_inline:
                sys.stdout.write("\n")
                self._last_inline = False
            if inline:  # not a terminal: fewer lines
                return
            sys.stdout.write(line + "\n")
        sys.stdout.flush()

    def always(self, text: str) -> None:
        self(text)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


class RosSession:
    """A roscore on a free port and the roslaunch processes of the demo; stops all of them on exit."""

    def __init__(self, log_dir: Path, progress: Progress) -> None:
        self.log_dir = log_dir
        self.progress = progress
        self.port = _free_port()
        self.procs: List[subprocess.Popen] = []
        self.env = dict(os.environ)
        self.env["ROS_MASTER_URI"] = f"http://localhost:{self.port}"
        self.env["ROS_HOSTNAME"] = "localhost"
        self.env.pop("ROS_IP", None)
        self.env["ROS_LOG_DIR"] = str(log_dir)
        self.env["PYTHONUNBUFFERED"] = "1"

    def __enter__(self) -> "RosSession":
        self.log_dir.mkdir(parents=True, exist_ok=True)
        os.environ.update({k: self.env[k] for k in ("ROS_MASTER_URI", "ROS_HOSTNAME", "ROS_LOG_DIR")})
        os.environ.pop("ROS_IP", None)
        self.core = self.spawn(["roscore", "-p", str(self.port)], "roscore")
        import rosgraph

        deadline = time.monotonic() + 30
        while not rosgraph.Master("/aruco_ring_demo").is_online():
            if time.monotonic() > deadline or self.core.poll() is not None:
                raise RuntimeError(f"roscore did not start on port {self.port} (log: {self.log_dir}/roscore.log)")
            time.sleep(0.2)
        return self

    def spawn(self, cmd: List[str], name: str) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "w")
        proc = subprocess.Popen(cmd, env=self.env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        log.close()
        self.procs.append(proc)
        return proc

    def launch(self, name: str, args: List[str]) -> subprocess.Popen:
        return self.spawn(["roslaunch", PACKAGE, "demo.launch"] + args, name)

    def stop(self, proc: subprocess.Popen, timeout: float = 15.0) -> None:
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGINT)
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
            except ProcessLookupError:
                pass
        if proc in self.procs:
            self.procs.remove(proc)

    def __exit__(self, *exc) -> None:
        for proc in reversed(list(self.procs)):
            self.stop(proc)


# --------------------------------------------------------------------------------------------
# The simulated lab: the simulator node's configuration for each phase, and what the demo records
# --------------------------------------------------------------------------------------------
def simulator_configs(args: argparse.Namespace, scene) -> Tuple[SimulatorConfig, SimulatorConfig]:
    """The simulator node's parameters for the mapping phase and for the localization phase.

    Mapping: the robot stands at the scene's mapping pose (the paper's single placement), no
    waypoints. Localization: the route is the mapping pose (the localizer starts where mapping
    left the robot), then the paper's stops in :func:`plan_stops` order, each held
    ``hold_frames`` frames, driven at up to 0.5 m/s; the clock runs as fast as the localizer
    answers (lockstep on ``localizer/pose``, and on the detectors in images mode).
    """
    base = with_overrides(SimulatorConfig(), {"mode": args.mode, "rate": args.rate, "seed": args.seed,
                                              "clock.publish": True})
    mapping = with_overrides(base, {"robot.waypoints": "none", "clock.speed": MAPPING_SPEED})
    route = [tuple(scene.mapping_pose)] + [s.pose for s in plan_stops(scene.test_positions, scene.test_orientations)]
    localization = with_overrides(base, {
        "robot.plan": [[float(x), float(y), float(np.degrees(yaw))] for x, y, yaw in route],
        "robot.hold_time": args.hold_frames / args.rate,
        "robot.limits.max_speed": DRIVE_SPEED,
        "clock.speed": LOCALIZATION_SPEED, "clock.start_time": LOCALIZATION_START,
        "lockstep.topics": ["localizer/pose"],
        "lockstep.timeout": LOCKSTEP_TIMEOUT[args.mode]})
    return mapping, localization


def write_simulator_config(path: Path, config: SimulatorConfig) -> Path:
    """The YAML the demo hands to ``simulation.launch config:=`` (kept beside the results)."""
    import yaml

    atomic_write_text(str(path), "# simulator parameters of one phase of make demo (config/simulator.yaml format)\n"
                      + yaml.safe_dump(to_dict(config), sort_keys=False), keep_backup=False)
    return path


def stop_frames(stamps: Sequence[float], truth: np.ndarray, route: Sequence[Sequence[float]], hold_time: float,
                tolerance: Tuple[float, float] = (0.01, np.radians(1.0))) -> List[List[float]]:
    """For each pose of the route, in order, the stamps of the frames at which the robot rested there.

    The robot is at rest where the ground truth stays put (``tr.detect_stops`` within 1 um /
    1 urad: a simulated robot at rest does not move at all) for most of ``hold_time``; each rest
    is matched to the next route pose within ``tolerance`` (m, rad: the driver stops within
    5 mm / 0.5 deg of a waypoint). A route pose with no rest gets an empty list. The frames of a
    rest are at most ``hold_time`` long (the robot stays at the last pose after the route ends).
    """
    s = np.asarray(stamps, dtype=float)
    r = np.asarray(truth, dtype=float).reshape(-1, 3)
    out: List[List[float]] = [[] for _ in route]
    j = 0
    for stop in tr.detect_stops(s, r, min_duration=0.6 * hold_time, pos_tol=1e-6, yaw_tol=1e-6):
        inside = np.flatnonzero((s >= stop.start - 1e-9) & (s <= stop.end + 1e-9))
        rest = r[inside[-1]]
        for k in range(j, len(route)):
            goal = np.asarray(route[k], dtype=float)
            close = np.hypot(*(rest[:2] - goal[:2])) <= tolerance[0]
            if close and abs(geo.angle_diff(rest[2], goal[2])) <= tolerance[1]:
                keep = inside[s[inside] <= s[inside[0]] + hold_time + 1e-9]
                out[k] = [float(v) for v in s[keep]]
                j = k + 1
                break
    return out


class Recorder:
    """What the demo collects, by stamp: the simulator's ground truth and the localizer's poses.

    Also counts the simulator's frames (``sim/ground_truth``) and follows its progress through the
    route (``sim/at_waypoint``: the index held, -1 while driving and once finished).
    """

    def __init__(self) -> None:
        import rospy
        from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
        from std_msgs.msg import Int32

        self.lock = threading.Condition()
        self.truth: Dict[float, np.ndarray] = {}
        self.poses: Dict[float, np.ndarray] = {}
        self.cam_estimates: Dict[float, np.ndarray] = {}
        self.held: List[int] = []          # sim/at_waypoint values, consecutive repeats removed
        self.frames = 0
        self.recording = True              # False: frames that still arrive are not kept
        rospy.Subscriber("/sim/ground_truth", PoseStamped, self._on_truth, queue_size=100)
        rospy.Subscriber("/sim/at_waypoint", Int32, self._on_waypoint, queue_size=100)
        rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, self._on_pose, queue_size=100)
        rospy.Subscriber("/localizer/camera_estimates", PoseArray, self._on_cams, queue_size=100)

    @staticmethod
    def _se2(pose) -> np.ndarray:
        from .conversions import pose_msg_to_transform
        return geo.se2_from_transform(pose_msg_to_transform(pose))

    def _on_truth(self, msg) -> None:
        with self.lock:
            if self.recording:
                self.truth[round(msg.header.stamp.to_sec(), 6)] = self._se2(msg.pose)
                self.frames += 1
                self.lock.notify_all()

    def _on_waypoint(self, msg) -> None:
        with self.lock:
            if not self.held or self.held[-1] != msg.data:
                self.held.append(int(msg.data))
                self.lock.notify_all()

    def _on_pose(self, msg) -> None:
        with self.lock:
            self.poses[round(msg.header.stamp.to_sec(), 6)] = self._se2(msg.pose.pose)
            self.lock.notify_all()

    def _on_cams(self, msg) -> None:
        arr = np.array([self._se2(p) for p in msg.poses]).reshape(-1, 3)
        with self.lock:
            self.cam_estimates[round(msg.header.stamp.to_sec(), 6)] = arr

    def clear(self) -> None:
        with self.lock:
            self.truth.clear()
            self.poses.clear()
            self.cam_estimates.clear()
            self.held.clear()
            self.frames = 0
            self.recording = True

    def wait(self, condition, timeout: float, alive=lambda: True) -> bool:
        """Wait (wall time) until ``condition()`` holds under the lock, while ``alive()``."""
        deadline = time.monotonic() + timeout
        with self.lock:
            while not condition():
                left = deadline - time.monotonic()
                if left <= 0 or not alive():
                    return False
                self.lock.wait(min(left, 0.5))
        return True


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------
MAPPING_SPEED = 2.0            # simulated s per wall s while mapping (no per-frame answer to wait for)
MAPPING_EXTRA_FRAMES = 3
LOCALIZATION_SPEED = 50.0      # as fast as the lockstep lets it
LOCALIZATION_START = 1000.0    # simulated clock of the localization phase, s
DRIVE_SPEED = 0.5              # m/s between stops
LOCKSTEP_TIMEOUT = {"images": 10.0, "corners": 3.0}   # wall s for one frame's answers


def _parse(argv: Optional[Sequence[str]]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m aruco_ring_localization.ros.demo",
                                description="The paper's experiment on the simulated lab with the real ROS nodes.")
    p.add_argument("--fusion", choices=("joint", "paper"), default="joint", help="localizer fusion (default joint)")
    p.add_argument("--method", choices=("refined", "paper"), default="refined", help="map method (default refined)")
    p.add_argument("--mode", choices=("images", "corners"), default=os.environ.get("DEMO_MODE", "auto"),
                   help="images: rendered images through the detector nodes; corners: simulated detections "
                        "(default: images when the detector node exists)")
    p.add_argument("--out", default=str(REPO / "results" / "demo"), help="output directory")
    p.add_argument("--gui", action="store_true", default=os.environ.get("GUI", "") not in ("", "0"),
                   help="also open rviz (needs DISPLAY); GUI=1 in the environment does the same")
    p.add_argument("--rate", type=float, default=5.0, help="simulated frames per simulated second")
    p.add_argument("--mapping-frames", type=int, default=30, help="frames at the mapping pose")
    p.add_argument("--hold-frames", type=int, default=10, help="frames held at each stop")
    p.add_argument("--use-last", type=int, default=5, help="last frames of each stop averaged (median)")
    p.add_argument("--seed", type=int, default=0, help="seed of the rig error, noise and rendering")
    args = p.parse_args(argv)
    if args.mode == "auto":
        args.mode = "images" if (REPO / "scripts" / "detector").exists() and \
            (REPO / "launch" / "detector.launch").exists() else "corners"
    if args.gui and not os.environ.get("DISPLAY"):
        sys.stdout.write("demo: GUI requested but DISPLAY is not set; running without rviz\n")
        args.gui = False
    return args


def _map(ros: RosSession, rec: Recorder, args: argparse.Namespace, config: SimulatorConfig, scene: Scene,
         common: List[str], progress: Progress) -> MarkerMap:
    """Mapping phase: the simulator holds the robot at the plate centre; save the map after the frames."""
    import rospy
    from std_srvs.srv import Trigger

    out = Path(args.out)
    sim_yaml = write_simulator_config(out / "simulator_mapping.yaml", config)
    mapping = ros.launch("mapping", ["phase:=mapping", f"method:={args.method}", f"sim_config:={sim_yaml}"] + common)
    rospy.wait_for_service("/mapper/save_map", timeout=120)
    with rec.lock:
        first = rec.frames
    pose = scene.mapping_pose
    progress(f"mapping from the plate centre ({pose[0]:.2f}, {pose[1]:.2f}) m: {args.mapping_frames} frames")
    # A few frames more than needed, so that the last ones are through the mapper too (it keeps
    # the first max_frames_per_station frames of a station, so extra ones change nothing).
    if not rec.wait(lambda: rec.frames >= first + args.mapping_frames + MAPPING_EXTRA_FRAMES, 600,
                    alive=lambda: mapping.poll() is None):
        raise RuntimeError(f"the simulator gave {rec.frames - first} of {args.mapping_frames} mapping frames "
                           f"(logs: {out / 'logs'}/mapping.log)")
    progress("mapping: /mapper/save_map" + (" (bundle adjustment)" if args.method == "refined" else ""))
    res = rospy.ServiceProxy("/mapper/save_map", Trigger)()
    if not res.success:
        raise RuntimeError(f"save_map failed: {res.message}")
    progress(f"mapping: {res.message}")
    ros.stop(mapping)
    return MarkerMap.load(str(out / "map.yaml"))


def _localize(ros: RosSession, rec: Recorder, args: argparse.Namespace, config: SimulatorConfig,
              stops: Sequence[StopPlan], common: List[str], progress: Progress) -> None:
    """Localization phase: the simulator drives the route in lockstep with the localizer; ``rec``
    keeps the route's frames (ground truth, poses) until it is done."""
    import rospy
    from std_srvs.srv import Trigger

    out = Path(args.out)
    sim_yaml = write_simulator_config(out / "simulator_localization.yaml", config)
    rec.clear()
    loc = ros.launch("localization", ["phase:=localization", f"fusion:={args.fusion}",
                                      f"comparison_dir:={out / 'comparison'}", f"sim_config:={sim_yaml}"] + common)
    progress(f"localization ({args.fusion} fusion): driving through {sum(s.kind == 'position' for s in stops)} "
             f"positions and {sum(s.kind == 'orientation' for s in stops)} orientations")
    finished = [len(stops), -1]   # sim/at_waypoint: the last stop held (route index 0 is the start), then done
    shown = 0
    while True:
        if not rec.wait(lambda: len(rec.held) > shown or rec.held[-2:] == finished, 1800,
                        alive=lambda: loc.poll() is None):
            raise RuntimeError(f"the localization phase stopped (logs: {out / 'logs'}/localization.log)")
        with rec.lock:
            held, frames, poses = list(rec.held), rec.frames, len(rec.poses)
        for k in held[shown:]:
            if k > 0:
                stop = stops[k - 1]
                progress(f"{stop.kind} {stop.label:>2}: holding ({stop.pose[0]:.2f}, {stop.pose[1]:.2f}, "
                         f"{np.degrees(stop.pose[2]):6.1f} deg) [{k}/{len(stops)}]; {frames} frames, {poses} poses")
        shown = len(held)
        if held[-2:] == finished:
            break
    with rec.lock:  # the route is done: keep its frames, and wait for their last poses
        rec.recording = False
    rec.wait(lambda: all(s in rec.poses for s in rec.truth), config.lockstep.timeout)
    try:  # the comparison node's own tables (live, fitted alignment): a cross-check
        rospy.wait_for_service("/comparison/write_tables", timeout=5)
        rospy.ServiceProxy("/comparison/write_tables", Trigger)()
    except (rospy.ROSException, rospy.ServiceException) as exc:
        progress(f"note: no tables from the comparison node ({exc})")
    ros.stop(loc)


def _records(rec: Recorder, stops: Sequence[StopPlan], route: Sequence[Sequence[float]], hold_time: float,
             use_last: int, progress: Progress) -> List[StopRecord]:
    """One :class:`StopRecord` per stop: the truth where the robot rested, the last poses there."""
    with rec.lock:
        truth, poses, cams = dict(rec.truth), dict(rec.poses), dict(rec.cam_estimates)
    stamps = sorted(truth)
    frames = stop_frames(stamps, np.array([truth[s] for s in stamps]), route, hold_time)
    records = []
    for stop, stamps_k in zip(stops, frames[1:]):
        record = StopRecord(stop, truth[stamps_k[-1]] if stamps_k else np.asarray(stop.pose, dtype=float))
        record.estimates = [(s, poses[s]) for s in stamps_k if s in poses][-use_last:]
        record.camera_estimates = next((list(cams[s]) for s in reversed(stamps_k) if len(cams.get(s, ()))), [])
        records.append(record)
        if not stamps_k:
            progress(f"note: no rest found at {stop.kind} {stop.label}")
    missed = sum(1 for s in stamps if s not in poses)
    if missed:
        progress(f"note: {missed} of {len(stamps)} frames have no pose (the localizer did not answer them within "
                 f"the lockstep timeout, or before its first fix); each stop uses the frames that have one")
    return records


def run(args: argparse.Namespace) -> int:
    progress = Progress()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = Scene.default()
    mapping_cfg, loc_cfg = simulator_configs(args, scene)
    route = [(x, y, float(np.radians(yaw))) for x, y, yaw in loc_cfg.robot.plan]
    stops = plan_stops(scene.test_positions, scene.test_orientations)
    progress(f"simulated lab '{scene.name}': {len(scene.markers)} markers, plate {scene.plate.size[0]:.2f} x "
             f"{scene.plate.size[1]:.2f} m; true rig = ring.yaml + "
             f"{1000 * loc_cfg.ring.calibration_trans_std:.0f} mm / {loc_cfg.ring.calibration_rot_std_deg:.1f} deg "
             f"calibration error; mode {args.mode}")
    common = [f"map_file:={out / 'map.yaml'}", f"mode:={args.mode}", f"gui:={'true' if args.gui else 'false'}"]
    with RosSession(out / "logs", progress) as ros:
        progress(f"roscore on port {ros.port} (logs: {out / 'logs'})")
        import rospy

        rospy.init_node("aruco_ring_demo", disable_signals=True)
        rec = Recorder()
        est_map = _map(ros, rec, args, mapping_cfg, scene, common, progress)
        _localize(ros, rec, args, loc_cfg, stops, common, progress)
        rospy.signal_shutdown("demo done")
    records = _records(rec, stops, route, loc_cfg.robot.hold_time, args.use_last, progress)
    with rec.lock:
        truth, poses = dict(rec.truth), dict(rec.poses)
    runtime = progress.elapsed()
    summary = write_report(out, records, est_map, scene.truth_map(), scene, sorted(poses.items()),
                           sorted(truth.items()), args.fusion, args.method, args.mode, runtime)
    sys.stdout.write("\n" + (out / "table1.md").read_text() + "\n" + (out / "table2.md").read_text() + "\n")
    m = summary["map_error_mm"]
    if m is not None:
        sys.stdout.write(f"Map error ({len(est_map)} markers, {args.method}): position RMS {m['rms']:.2f} mm, max "
                         f"{m['max']:.2f} mm; rotation mean {m['rotation_mean_deg']:.3f} deg\n\n")
    c = summary.get("after_best_fit_se2")
    if c:
        sys.stdout.write(f"After a best-fit SE(2) alignment (internal consistency only, the map frame's error removed: "
                         f"{c['alignment']['x_m'] * 100:+.1f} cm, {c['alignment']['y_m'] * 100:+.1f} cm, "
                         f"{c['alignment']['yaw_deg']:+.2f} deg): position median "
                         f"{c['position_error_cm']['median']:.2f} cm, max {c['position_error_cm']['max']:.2f} cm; "
                         f"|yaw| mean {c['yaw_error_deg']['mean_abs']:.3f} deg\n\n")
    sys.stdout.write("SUMMARY: " + summary_line(summary) + "\n")
    sys.stdout.write(f"outputs in {out}/ (summary.json, table1.md, table2.md, *.tum, *.png)\n")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args = _parse(argv)

    def _terminate(signum, _frame):  # so that `timeout`/CI stopping us still stops our roscore and nodes
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, _terminate)
    try:
        return run(args)
    except KeyboardInterrupt:
        sys.stderr.write("demo: interrupted\n")
        return 130
    except (RuntimeError, ArucoRingError) as exc:
        sys.stderr.write(f"demo: error: {exc}\n")
        return 1


if __name__ == "__main__":
    sys.exit(main())
