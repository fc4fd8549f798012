#!/usr/bin/env python3
"""Free-running cameras and odometry in the filter (issue 12, items 3 and 4).

The simulated lab in corners mode (projected corners + 0.3 px noise), the exact rig declared
exact, the true map, cameras at 10 Hz, the robot driving through the paper's test positions at up
to 0.5 m/s (SimRobot, its drifting wheel odometry at 50 Hz). Each camera's detections carry their
own stamp and reach the pipeline 20 ms later, one message per camera, in arrival order, as in the
node. Cases:

* ``synchronized``: every camera at the same instant (the reference);
* ``free``: camera k at phase k x 12.5 ms (spread over 87.5 ms of the 100 ms period) + 2 ms jitter
  (1 sigma), the stock ``input.slop: auto`` (a ring frame is one frame period measured from the
  stamps: it holds one frame of each camera, nothing hand-set); with
  ``motion.compensate_stamps`` (the default) and without (the estimator as before: every camera
  at the ring frame's stamp);
* ``odometry``: the same free-running cameras with ``motion.odometry``: the pose at the odometry
  rate, and a 5 s marker blackout while driving (the cameras report, but no marker).

Errors: each pose the pipeline outputs for a ring frame against the true pose at its stamp,
after the first 3 s (the track settled); the blackout error is the last output's just before
the markers come back (the odometry's drift over 5 s, about 2.5 m driven).
"""
from __future__ import annotations

import os
import sys
import time
from typing import Dict, List, Optional, Tuple

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.config import with_overrides  # noqa: E402
from aruco_ring_localization.detections import MarkerObservation  # noqa: E402
from aruco_ring_localization.pipeline import LocalizationPipeline  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.schemas import LocalizerConfig  # noqa: E402
from aruco_ring_localization.simulation.motion import SimRobot  # noqa: E402
from aruco_ring_localization.simulation.params import MotionLimits  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

RING_FILE = os.path.join(os.path.dirname(HERE), "config", "ring.yaml")
PIXEL_NOISE = 0.3
CAMERA_PERIOD = 0.1
ODOM_PERIOD = 0.02
LATENCY = 0.02
SIM_DT = 0.002
SPEED = 0.5
OFFLINE = {"input.use_tf": False, "input.camera_info_fallback": True}


class Drive:
    """The robot's true pose and odometry sampled every ``SIM_DT`` s while it drives."""

    def __init__(self, scene: Scene, waypoints: int, seed: int = 5):
        wps = list(scene.test_positions)[:waypoints]
        robot = SimRobot(wps[0], wps[1:], hold_time=0.5, seed=seed,
                         limits=MotionLimits(max_speed=SPEED, max_yaw_rate=0.8, max_accel=1.0))
        t, ts, poses, odom, vel = 0.0, [0.0], [robot.base.pose.copy()], [robot.odometry.pose.copy()], [np.zeros(3)]
        while robot.driving and t < 200.0:
            t += SIM_DT
            st = robot.step(t, SIM_DT)
            ts.append(t)
            poses.append(st.pose.copy())
            odom.append(st.odom_pose.copy())
            vel.append(st.odom_velocity.copy())
        self.t = np.array(ts)
        self.pose = np.array(poses)
        self.odom = np.array(odom)
        self.odom_velocity = np.array(vel)
        self.duration = float(self.t[-1])
        speed = np.hypot(*np.diff(self.pose[:, :2], axis=0).T) / SIM_DT
        self.max_speed = float(speed.max())
        self.mean_speed_moving = float(speed[speed > 0.05].mean())

    def _index(self, t: float) -> int:
        return int(np.clip(round(t / SIM_DT), 0, len(self.t) - 1))

    def true_pose(self, t: float) -> np.ndarray:
        return self.pose[self._index(t)]

    def odom_at(self, t: float) -> Tuple[np.ndarray, np.ndarray]:
        k = self._index(t)
        return self.odom[k], self.odom_velocity[k]


def _events(drive: Drive, sim: RingSimulator, phases: np.ndarray, jitter: float, rng,
            blackout: Optional[Tuple[float, float]]) -> List[tuple]:
    """(arrival time, kind, payload) of every message, in arrival order."""
    ev = []
    names = sim.ring.names
    k = 0
    while True:
        t0 = k * CAMERA_PERIOD
        if t0 + CAMERA_PERIOD > drive.duration:
            break
        for c, name in enumerate(names):
            t = t0 + phases[c] + (rng.normal(0.0, jitter) if jitter > 0 else 0.0)
            t = float(np.clip(t, 0.0, drive.duration))
            T = Scene.T_world_base(drive.true_pose(t))
            dark = blackout is not None and blackout[0] <= t < blackout[1]
            obs = [] if dark else [MarkerObservation(m, corners + rng.normal(0.0, PIXEL_NOISE, corners.shape))
                                   for m, corners in sim.visible_camera(T, name)]
            ev.append((t + LATENCY, "cam", (name, t, obs)))
        k += 1
    n = int(drive.duration / ODOM_PERIOD)
    for j in range(1, n):
        t = j * ODOM_PERIOD
        pose, vel = drive.odom_at(t)
        ev.append((t + 0.002, "odom", (t, pose, vel)))
    ev.sort(key=lambda e: e[0])
    return ev


def _run(drive: Drive, scene: Scene, ring: CameraRing, phases, jitter: float, overrides: Dict,
         blackout: Optional[Tuple[float, float]] = None, seed: int = 11,
         true_ring: Optional[CameraRing] = None) -> Dict[str, float]:
    """The pipeline (``ring`` its calibration) on the drive seen by ``true_ring`` (default ``ring``)."""
    rng = np.random.default_rng(seed)
    sim = RingSimulator(scene, ring if true_ring is None else true_ring, pixel_noise=0.0, seed=seed)
    config = with_overrides(LocalizerConfig(), {**OFFLINE, **overrides})
    pipe = LocalizationPipeline(config, ring, scene.truth_map())
    events = _events(drive, sim, np.asarray(phases), jitter, rng, blackout)
    errs: List[float] = []
    outputs, odom_outputs = 0, 0
    cpu = 0.0
    before_return: Optional[float] = None
    est_errs: List[float] = []      # the estimator's per-frame pose (before the gate and the filter)
    best_errs: List[float] = []     # per frame, the camera whose own PnP is nearest the truth (an oracle)
    nees: List[float] = []          # e^T P^-1 e / 3 over (x, y, yaw) with the estimator's own covariance
    last = None
    for now, kind, payload in events:
        c0 = time.thread_time()
        if kind == "cam":
            name, t, obs = payload
            out = pipe.on_detections(name, t, obs, now)
        else:
            t, pose, vel = payload
            out = pipe.on_motion("odom", t, vel[:2], float(vel[2]), now, T_odom_base=Scene.T_world_base(pose))
        out += pipe.poll(now)
        cpu += time.thread_time() - c0
        track = pipe.last_track
        if track is not None and track is not last:
            last = track
            loc = track.localization
            if loc.stamp >= 3.0 and not (blackout is not None and blackout[0] <= loc.stamp < blackout[1] + 1.0):
                truth = Scene.T_world_base(drive.true_pose(loc.stamp))
                est_errs.append(_planar_error(loc.T_map_base, truth))
                if loc.ok and loc.covariance_se2 is not None:
                    e = geo.se2_from_transform(loc.T_map_base) - geo.se2_from_transform(truth)
                    e[2] = geo.wrap_angle(e[2])
                    nees.append(float(e @ np.linalg.solve(loc.covariance_se2, e)) / 3.0)
                own = [_planar_error(c.T_map_base, truth) for c in loc.estimates.values() if c.valid]
                best_errs.append(min(own) if own else float("inf"))
        for o in out:
            outputs += 1
            odom_outputs += int(o.from_odometry)
            truth = Scene.T_world_base(drive.true_pose(o.stamp))
            e = float(np.hypot(*(o.T_map_base[:2, 3] - truth[:2, 3])))
            if blackout is not None and o.stamp < blackout[1]:
                before_return = e
            if o.from_odometry or o.predicted_only or o.stamp < 3.0:
                continue
            if blackout is not None and blackout[0] <= o.stamp < blackout[1] + 1.0:
                continue
            errs.append(e)
    return {"median_cm": 100 * float(np.median(errs)), "max_cm": 100 * float(np.max(errs)),
            "frames": len(errs), "ring_frames": pipe.input.ring_frames_out,
            "split_frames": sum(pipe.input.assembler.incomplete.values()), "rate_hz": outputs / drive.duration, "odom_rate_hz": odom_outputs / drive.duration,
            "blackout_cm": float("nan") if before_return is None else 100 * before_return,
            "cpu_ms_per_output": 1000.0 * cpu / max(outputs, 1),
            "estimator_median_cm": 100 * float(np.median(est_errs)) if est_errs else float("nan"),
            "estimator_max_cm": 100 * float(np.max(est_errs)) if est_errs else float("nan"),
            "best_camera_median_cm": 100 * float(np.median(best_errs)) if best_errs else float("nan"),
            "estimator_frames": len(est_errs),
            "estimator_nees": float(np.mean(nees)) if nees else float("nan")}


def _planar_error(T_est: Optional[np.ndarray], T_true: np.ndarray) -> float:
    """Position error in the plane, m (inf: no pose: counted as a miss, never dropped)."""
    if T_est is None:
        return float("inf")
    return float(np.hypot(*(T_est[:2, 3] - T_true[:2, 3])))


#: The ablation while driving (issue 12: joint <= paper and <= the best camera in every configuration).
ABLATION_FUSIONS = ("paper", "joint")
#: The simulated ring is rigid (no vibration): the ablation declares it so, as bench_localization's
#: kind lab does (estimator/extrinsic_jitter_*; the stock 0.05 deg is the harsh lab's). Declared, a
#: vibration the ring does not have made the exact-extrinsics pose's covariance (frames whose
#: cameras agree) 2.5 times too large in std (NEES 0.15 synchronized/exact).
RIGID = {"estimator.extrinsic_jitter_deg": 0.0, "estimator.extrinsic_jitter_m": 0.0}


def _moving_ablation(drive: Drive, scene: Scene, ring: CameraRing, phases: Dict[str, np.ndarray],
                     jitter: float) -> Dict[Tuple[str, str], Dict[str, Dict[str, float]]]:
    """Per-frame estimator errors of the paper's fusion and the joint estimate (and the best single
    camera, from the paper run's own per-camera PnPs) while driving, synchronized and free-running,
    with the exact rig declared exact and with the ring file's extrinsics (the true rig 2 mm /
    0.2 deg off it, declared with the ring file's std); the ring declared rigid (:data:`RIGID`, as
    it is). Defaults otherwise (compensation on)."""
    true_ring = perturb_ring(ring, seed=1)
    configs = {"exact": (ring.with_extrinsics_std(0.0, 0.0), ring),
               "ring_file": (ring, true_ring)}
    out: Dict[Tuple[str, str], Dict[str, Dict[str, float]]] = {}
    for cam_name, ph in phases.items():
        for cfg, (est_ring, truth_ring) in configs.items():
            per: Dict[str, Dict[str, float]] = {}
            for fusion in ABLATION_FUSIONS:
                r = _run(drive, scene, est_ring, ph, jitter if cam_name == "free" else 0.0,
                         {"estimator.fusion": fusion, **RIGID}, true_ring=truth_ring)
                per[fusion] = {"median_cm": r["estimator_median_cm"], "max_cm": r["estimator_max_cm"],
                               "frames": r["estimator_frames"], "nees": r["estimator_nees"]}
                if fusion == "paper":
                    per["best_camera"] = {"median_cm": r["best_camera_median_cm"]}
            out[(cam_name, cfg)] = per
    return out


def run(quick: bool = False) -> dict:
    scene = Scene.default()
    ring = CameraRing.load(RING_FILE).with_extrinsics_std(0.0, 0.0)
    drive = Drive(scene, waypoints=5 if quick else 15)
    n = len(ring.names)
    sync = np.zeros(n)
    free = np.arange(n) * (0.0875 / (n - 1))
    jitter = 0.002
    slop: Dict[str, object] = {}  # the stock input.slop (auto): nothing tuned to the cameras' phases
    r_sync = _run(drive, scene, ring, sync, 0.0, {})
    r_unc = _run(drive, scene, ring, free, jitter, {**slop, "motion.compensate_stamps": False})
    r_comp = _run(drive, scene, ring, free, jitter, slop)
    r_odom = _run(drive, scene, ring, free, jitter, {**slop, "motion.odometry": True})
    # The blackout where the robot drives farthest in 5 s (while driving, not holding at a waypoint).
    step = np.hypot(*np.diff(drive.pose[:, :2], axis=0).T)
    w = int(round(5.0 / SIM_DT))
    dist = np.convolve(step, np.ones(w), mode="valid")
    k_min = int(round(5.0 / SIM_DT))   # after the track settled
    k_b = k_min + int(np.argmax(dist[k_min:len(dist) - int(round(3.0 / SIM_DT))]))
    t_b = float(drive.t[k_b])
    blackout = (t_b, t_b + 5.0)
    r_black = _run(drive, scene, ring, free, jitter, {**slop, "motion.odometry": True}, blackout=blackout)
    r_black_no = _run(drive, scene, ring, free, jitter, slop, blackout=blackout)
    abl = _moving_ablation(drive, scene, CameraRing.load(RING_FILE), {"synchronized": sync, "free": free}, jitter)
    ratios = {k: per["joint"]["median_cm"] / min(per["paper"]["median_cm"], per["best_camera"]["median_cm"])
              for k, per in abl.items()}
    k0, k1 = drive._index(blackout[0]), drive._index(blackout[1])
    driven = float(np.sum(np.hypot(*np.diff(drive.pose[k0:k1 + 1, :2], axis=0).T)))
    results = {
        "moving_pos_err_cm_median": r_comp["median_cm"],
        "moving_pos_err_cm_max": r_comp["max_cm"],
        "moving_pos_err_cm_median_uncompensated": r_unc["median_cm"],
        "moving_pos_err_cm_max_uncompensated": r_unc["max_cm"],
        "moving_pos_err_cm_median_synchronized": r_sync["median_cm"],
        "moving_pos_err_cm_max_synchronized": r_sync["max_cm"],
        "moving_pos_err_cm_median_with_odom": r_odom["median_cm"],
        "moving_pos_err_cm_max_with_odom": r_odom["max_cm"],
        "pose_rate_hz_with_odom": r_odom["rate_hz"],
        "pose_rate_hz_without_odom": r_comp["rate_hz"],
        "blackout_5s_err_cm": r_black["blackout_cm"],
        "blackout_5s_err_cm_without_odom": r_black_no["blackout_cm"],
        "motion_cpu_ms_per_output_with_odom": r_odom["cpu_ms_per_output"],
        "joint_vs_best_ratio_worst_moving": max(ratios.values()),
        # the configuration farthest from 1 (1 = the covariance is honest)
        "nees_joint_moving": max((per["joint"]["nees"] for per in abl.values()), key=lambda v: abs(np.log(v))),
    }
    for (cams, cfg), per in abl.items():
        for est, m in per.items():
            results[f"moving_est_err_cm_median_{est}_{cams}_{cfg}"] = m["median_cm"]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    rows = [("synchronized cameras", r_sync), ("free-running, **not compensated**", r_unc),
            ("free-running, compensated (default)", r_comp), ("free-running, compensated, odometry in the filter", r_odom)]
    lines = [
        "## Free-running cameras and odometry (issue 12)",
        "",
        f"bench/bench_motion.py. Simulated lab, corners mode ({PIXEL_NOISE} px), exact rig declared exact, true map; "
        f"8 cameras at 10 Hz; the robot drives through {5 if quick else 15} test positions in "
        f"{drive.duration:.0f} s (up to {drive.max_speed:.2f} m/s, {drive.mean_speed_moving:.2f} m/s on average while "
        f"moving), its drifting wheel odometry (1 % scale error) on odom at 50 Hz; each message reaches the "
        f"pipeline {1000 * LATENCY:.0f} ms after its stamp. Free-running: camera k at phase k x 12.5 ms, 2 ms "
        "jitter, the stock `input.slop` (auto). Errors of the outputs for ring frames against the truth at their "
        "stamps, after 3 s.",
        "",
        "| cameras | position median (cm) | position max (cm) | ring frames (without every camera) | poses out (Hz) |",
        "|---|---|---|---|---|",
    ]
    for label, r in rows:
        lines.append(f"| {label} | {r['median_cm']:.3f} | {r['max_cm']:.2f} | {r['ring_frames']} ({r['split_frames']}) "
                     f"| {r['rate_hz']:.1f} |")
    lines += [
        "",
        f"Keys: `moving_pos_err_cm_median` {results['moving_pos_err_cm_median']:.3f} (target <= 1.0), "
        f"`moving_pos_err_cm_max` {results['moving_pos_err_cm_max']:.2f} (target <= 3), "
        f"`moving_pos_err_cm_median_uncompensated` {results['moving_pos_err_cm_median_uncompensated']:.3f}; "
        f"`pose_rate_hz_with_odom` {results['pose_rate_hz_with_odom']:.1f} (target >= 50: a pose for every odom "
        "message, 50 Hz, and one for every ring frame, 10 Hz).",
        "",
        f"Marker blackout: from {blackout[0]:.1f} s for 5 s ({driven:.2f} m driven) every camera reports no marker; "
        f"the position error just before the markers return: **{results['blackout_5s_err_cm']:.2f} cm** with "
        f"odometry in the filter (`blackout_5s_err_cm`, target <= 5), "
        f"{results['blackout_5s_err_cm_without_odom']:.1f} cm with the paper's constant-acceleration prediction "
        "(`blackout_5s_err_cm_without_odom`)."
        " The constant-acceleration prediction holds only while the robot keeps its velocity (a straight stretch "
        "at constant speed); turning or stopping in the dark it does not: on a 0.5 m/s circle it is more than 5 times "
        "the odometry's error after 5 s (test/unit/test_motion.py), and the rostest motion.test bridges 5 s on a circle.",
        "",
        "**Estimators while driving** (issue 12's ablation in the configurations the resting lab of "
        "`## Localization` cannot show: synchronized and free-running cameras on a moving robot): the per-frame "
        "estimate (before the gate and the filter) of each fusion, through the stock pipeline (stamps "
        "compensated), against the truth at the frame's stamp; *exact*: the ring file is the true rig and "
        "declared exact; *ring file*: the true rig 2 mm / 0.2 deg per axis off the ring file (seed 1), the "
        "ring file's std declared; both declare the ring rigid (`estimator/extrinsic_jitter_*` 0: the simulated ring "
        "does not vibrate). *Best camera*: per frame the one camera whose own PnP is nearest the truth "
        "(an oracle, from the paper run). A frame without a pose counts as a miss (infinite error).",
        "",
        "| cameras | extrinsics | paper median / max (cm) | joint median / max (cm) | best camera median (cm) "
        "| joint / min(paper, best) | NEES joint |",
        "|---|---|---|---|---|---|---|",
    ]
    for (cams, cfg), per in abl.items():
        lines.append(f"| {cams} | {cfg.replace('_', ' ')} | {per['paper']['median_cm']:.3f} / "
                     f"{per['paper']['max_cm']:.2f} | {per['joint']['median_cm']:.3f} / {per['joint']['max_cm']:.2f} "
                     f"| {per['best_camera']['median_cm']:.3f} | {ratios[(cams, cfg)]:.2f} "
                     f"| {per['joint']['nees']:.2f} |")
    lines += [
        "",
        f"`joint_vs_best_ratio_worst_moving` = {results['joint_vs_best_ratio_worst_moving']:.2f} (target <= 1.0; "
        "the resting labs' worst is `joint_vs_best_ratio_worst`); `nees_joint_moving` = "
        f"{results['nees_joint_moving']:.2f} (the configuration farthest from 1; NEES = mean of e^T P^-1 e / 3 over "
        "(x, y, yaw) with the estimator's own covariance; target 0.5-2 as `nees_joint`).",
        "",
        f"CPU per output with odometry (camera frames and odometry steps together): "
        f"{results['motion_cpu_ms_per_output_with_odom']:.2f} ms (load average {load:.1f}).",
    ]
    return {"results": results, "markdown": "\n".join(lines)}


if __name__ == "__main__":
    import json

    out = run(quick="--quick" in sys.argv)
    print(json.dumps(out["results"], indent=2))
    print(out["markdown"])
