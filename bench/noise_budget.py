"""Where the joint estimator's error comes from in the harsh lab (issue 12, item 1): an error budget.

The harsh lab (config/lab_harsh.yaml) adds to the kind one a tilted, bumpy plate, ring vibration,
a wandering gain and uneven light (and pillars, which only hide markers). This script renders the
benchmark's image-mode frames (bench/bench_localization.py: same rig, seeds, poses and detector)
with each of those switched off in turn, rebuilds the map in that lab, and runs the estimators of
the localization benchmark in its three configurations (exact, ring-file and refined extrinsics).
For the exact configuration it also reports

* ``px_rms``: the detector's own corner error, RMS per coordinate, against the true projection
  through the camera as it was (shaken) in that frame: the pixel noise the images really have;
* ``px_rms_nominal``: the same against the projection through the ring as calibrated (rigid):
  what the vibration adds in pixels;
* ``joint_true_shake``: the joint estimate given each frame's true (shaken) extrinsics, declared
  exact: the error left without the vibration, with the same images.

Usage: ``python bench/noise_budget.py [--quick] [--variants harsh,no_vibration,...] [--cache DIR]``;
prints one table (markdown) and the numbers as JSON. ``--cache DIR`` keeps the rendered frames and
maps (pickles) so that estimator changes can be re-measured without rendering again.
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
from typing import Dict, List, Optional

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_localization as bl  # noqa: E402
from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.config import with_overrides  # noqa: E402
from aruco_ring_localization.detections import CameraFrame, RingFrame  # noqa: E402
from aruco_ring_localization.localization import LocalizationParams, RingLocalizer  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.simulation.conditions import LabConditions  # noqa: E402
from aruco_ring_localization.simulation.params import lab_config  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene, resolve_scene_file  # noqa: E402

#: What each variant switches off in the harsh lab.
VARIANTS = {
    "harsh": {},
    "no_vibration": {"ring.vibration_rot_std_deg": 0.0, "ring.vibration_trans_std": 0.0},
    "flat": {"plate.tilt_deg": 0.0, "plate.bump_deg": 0.0},
    "no_photometry": {"render.gain_std": 0.0, "render.illumination_gradient": 0.0},
    "none": {"ring.vibration_rot_std_deg": 0.0, "ring.vibration_trans_std": 0.0, "plate.tilt_deg": 0.0,
             "plate.bump_deg": 0.0, "render.gain_std": 0.0, "render.illumination_gradient": 0.0},
}


def render_frames(scene: Scene, true_ring: CameraRing, cond: LabConditions, per_pose: int):
    """As bench_localization._rendered_frames (same seeds and draws), also keeping each frame's
    per-camera view poses (the shaken base) and true corners."""
    sim = RingSimulator(scene, true_ring, pixel_noise=0.0, seed=11)
    det = bl._detector(scene.dictionary)
    rng = np.random.default_rng(12)
    poses = list(scene.test_positions) + list(scene.test_orientations)
    out = []
    for k, p in enumerate(poses):
        T_world = cond.T_world_base(p)
        for j in range(per_pose):
            stamp = 10.0 * k + 0.1 * j
            light = cond.photometry.draw()
            views = cond.views(sim.ring, T_world)
            frame = RingFrame(stamp=stamp)
            truth_px = {}
            for c, Tv in views.items():
                img = sim.render_views([Tv], c, light.get(c), rng=rng)
                frame.cameras[c] = CameraFrame(c, stamp, det.detect(img))
                truth_px[c] = {"shaken": dict(sim.visible_camera(Tv, c)), "rigid": dict(sim.visible_camera(T_world, c))}
            out.append((k, T_world, frame, views, truth_px))
    return out


def pixel_errors(frames) -> Dict[str, float]:
    """RMS per coordinate of detected minus true corners (shaken and rigid projections)."""
    sq = {"shaken": [], "rigid": []}
    for _, _, frame, _, truth_px in frames:
        for c, cf in frame.cameras.items():
            for o in cf.observations:
                for kind in sq:
                    t = truth_px[c][kind].get(int(o.marker_id))
                    if t is not None:
                        sq[kind].append(np.asarray(o.corners) - t)
    return {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in sq.items()}


def joint_true_shake(frames, true_ring: CameraRing, truth) -> Dict[str, float]:
    """The joint estimator given each frame's true (shaken) extrinsics, declared exact."""
    errors, nees = [], []
    params = LocalizationParams(fusion="joint")
    for _, T_world, frame, views, _ in frames:
        ext = {c: geo.inverse(T_world) @ Tv @ true_ring[c].T_base_cam for c, Tv in views.items()}
        ring = true_ring.with_extrinsics(ext).with_extrinsics_std(0.0, 0.0)
        res = RingLocalizer(ring, truth, params).process(frame)
        if res.T_map_base is None:
            errors.append(np.array([np.inf, np.inf, np.pi]))
            continue
        e = bl._se2_error(res.T_map_base, T_world)
        errors.append(e)
        nees.append(float(e @ np.linalg.solve(res.covariance_se2, e)) / 3.0)
    return bl._summary(errors, nees)


def run_variant(name: str, per_pose: int, map_frames: int, cache: Optional[str]) -> Dict[str, Dict]:
    ring = CameraRing.load(bl.RING_FILE)
    true_ring = perturb_ring(ring, seed=bl.RIG_SEED)
    config = with_overrides(lab_config("harsh"), VARIANTS[name])
    scene = Scene.load(resolve_scene_file(config.scene.file))
    path = None if cache is None else os.path.join(cache, f"{name}_{per_pose}_{map_frames}.pkl")
    if path is not None and os.path.exists(path):
        with open(path, "rb") as fh:
            frames, marker_map, refined_ring = pickle.load(fh)
    else:
        # One conditions object for the map and the frames, as the benchmark (the same draws).
        cond = LabConditions(config, scene, ring.names, seed=bl.RIG_SEED)
        marker_map, _, refined_ring = bl._build_map(scene, ring, true_ring, frames=map_frames, conditions=cond)
        frames = render_frames(scene, true_ring, cond, per_pose)
        if path is not None:
            with open(path, "wb") as fh:
                pickle.dump((frames, marker_map, refined_ring), fh)
    truth = scene.truth_map()
    T_map_world = bl._map_to_world(marker_map, truth)
    configs = {"exact": (true_ring.with_extrinsics_std(0.0, 0.0), truth, np.eye(4)),
               "ring_file": (ring, bl._without_ring_calibration(marker_map), T_map_world)}
    if refined_ring is not None:
        configs["refined"] = (ring, marker_map, T_map_world)
    simple = [(k, T, f) for k, T, f, _, _ in frames]
    out = {c: bl._accuracy(simple, cfg) for c, cfg in configs.items()}
    out["exact"]["joint_true_shake"] = joint_true_shake(frames, true_ring, truth)
    px = pixel_errors(frames)
    out["pixels"] = {"px_rms": px["shaken"], "px_rms_nominal": px["rigid"]}
    return out


def markdown(results: Dict[str, Dict]) -> str:
    lines = ["| lab | extrinsics | estimator | position median (cm) | position max (cm) | yaw mean (deg) | NEES |",
             "|---|---|---|---|---|---|---|"]
    for var, per in results.items():
        for c in ("exact", "ring_file", "refined"):
            if c not in per:
                continue
            for est, m in per[c].items():
                nees = f"{m['nees']:.2f}" if "nees" in m else ""
                lines.append(f"| {var} | {c} | {est} | {m['pos_median_cm']:.3f} | {m['pos_max_cm']:.2f} | "
                             f"{m['yaw_mean_deg']:.3f} | {nees} |")
    lines += ["", "| lab | detector px RMS (true, shaken camera) | px RMS against the rigid ring |", "|---|---|---|"]
    for var, per in results.items():
        lines.append(f"| {var} | {per['pixels']['px_rms']:.3f} | {per['pixels']['px_rms_nominal']:.3f} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 frame per pose, 5 mapping frames per station")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated: " + ", ".join(VARIANTS))
    ap.add_argument("--cache", default=None, help="folder for rendered frames and maps (pickles)")
    args = ap.parse_args(argv)
    if args.cache:
        os.makedirs(args.cache, exist_ok=True)
    results = {}
    for name in args.variants.split(","):
        if name not in VARIANTS:
            ap.error(f"unknown variant {name!r}; expected one of {list(VARIANTS)}")
        results[name] = run_variant(name, 1 if args.quick else 2, 5 if args.quick else 10, args.cache)
        print(f"{name} done", file=sys.stderr, flush=True)
    print(markdown(results))
    print(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
