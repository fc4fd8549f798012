"""Is calibrate-ring's per-camera std honest? A Monte-Carlo on the simulated lab (corners mode).

The same true rig (config/ring.yaml perturbed, seed 1), the same rough ring (seed 5) and the same
drive (a full turn at each of the first ``--stations`` mapping stations, straight drives between),
the corner noise drawn again for each of ``--runs`` seeds (0.3 px, independent per corner and
frame: what the std's model assumes). Each run: :func:`ring_calibration.calibrate_ring` without
odometry or map; each camera's error relative to the others (the ring's common motion fitted out,
the gauge of the std) in its optical frame, against the std the run reported. Printed: per axis
group, the spread over the runs (RMS of the errors) over the mean reported std, and the RMS of
error / std over every camera, axis and run (1 for an honest std).

    python bench/run.py --only calibration_std        # both modes, written to docs/benchmarks.md
    python bench/bench_calibration_std.py [--runs 8] [--stations 3] [--images]   # one mode, printed

With ``--images`` the frames are rendered and detected (:class:`detection.Detector`) instead: the
corner errors are then the detector's, correlated from one frame to the next (the same marker
seen again from nearly the same place), not the independent noise the std's model assumes.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.markers import MarkerSizes  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ring_calibration import CalibrationOptions, calibrate_ring  # noqa: E402
from aruco_ring_localization.simulation.calibration_run import calibration_poses, rough_ring  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

RING_FILE = os.path.join(os.path.dirname(HERE), "config", "ring.yaml")


def relative_errors(true: CameraRing, est: CameraRing) -> np.ndarray:
    """(C, 6) error of each camera (rotation vector rad, translation m, optical frame) after the
    ring's common motion is fitted out."""
    G = geo.average_transforms([c.T_base_cam @ geo.inverse(est[c.name].T_base_cam) for c in true])
    out = []
    for c in true:
        D = geo.inverse(c.T_base_cam) @ G @ est[c.name].T_base_cam
        out.append(np.r_[geo.rvec_from_rotation(D[:3, :3]), D[:3, 3]])
    return np.array(out)


def _observe(sim, scene, poses, images: bool):
    from aruco_ring_localization.detection import Detector, DetectorParams
    from aruco_ring_localization.detections import CameraFrame, RingFrame

    if not images:
        return [sim.observe(Scene.T_world_base(p), stamp=0.1 * k) for k, p in enumerate(poses)]
    detectors = {}
    frames = []
    for k, p in enumerate(poses):
        t = 0.1 * k
        imgs = sim.render(Scene.T_world_base(p))
        for n in imgs:
            detectors.setdefault(n, Detector(DetectorParams(dictionary=scene.dictionary)))
        frames.append(RingFrame(t, {n: CameraFrame(n, t, detectors[n].detect(img)) for n, img in imgs.items()}))
    return frames


def run_mc(runs: int, stations: int, pixel_noise: float = 0.3, turn_step: float = 8.0, images: bool = False) -> dict:
    scene = Scene.default()
    true = perturb_ring(CameraRing.load(RING_FILE), seed=1)
    rough = rough_ring(true, seed=5)
    poses = calibration_poses(scene.mapping_stations[:stations], turn_step_deg=turn_step, drive_step=0.1)
    sizes = MarkerSizes(scene.markers[0].size)
    errs, stds, infl = [], [], []
    cpu = 0.0
    for seed in range(runs):
        sim = RingSimulator(scene, true, pixel_noise=pixel_noise, seed=100 + seed)
        frames = _observe(sim, scene, poses, images)
        t0 = time.process_time()
        cal = calibrate_ring(frames, rough, sizes, options=CalibrationOptions(max_frames=len(frames)))
        cpu += time.process_time() - t0
        errs.append(relative_errors(true, cal.ring))
        stds.append(np.array([cal.std[c.name] for c in true]))
        infl.append(cal.extra.get("std_inflation", 1.0))
    E, S = np.array(errs), np.array(stds)          # (runs, C, 6)
    z = E / S
    zr = E / (S / np.array(infl)[:, None, None])   # against the std without the correlation's inflation
    out = {"mode": "images" if images else "corners", "runs": runs, "frames": len(poses),
           "cpu_s_per_run": cpu / runs, "load": os.getloadavg()[0], "std_inflation": [float(v) for v in infl],
           "rot_z_rms_uninflated": float(np.sqrt(np.mean(zr[:, :, :3] ** 2))),
           "trans_z_rms_uninflated": float(np.sqrt(np.mean(zr[:, :, 3:] ** 2)))}
    for name, sl in (("rot", slice(0, 3)), ("trans", slice(3, 6))):
        spread = np.sqrt(np.mean(E[:, :, sl] ** 2, axis=0))            # (C, 3) over runs
        reported = np.mean(S[:, :, sl], axis=0)
        out[f"{name}_spread_over_std_median"] = float(np.median(spread / reported))
        out[f"{name}_spread_over_std_range"] = [float(np.min(spread / reported)), float(np.max(spread / reported))]
        out[f"{name}_z_rms"] = float(np.sqrt(np.mean(z[:, :, sl] ** 2)))
        out[f"{name}_bias_over_spread_median"] = float(np.median(np.abs(np.mean(E[:, :, sl], axis=0)) / spread))
        out[f"{name}_spread_max"] = float(np.max(spread)) * (1000.0 if name == "trans" else np.degrees(1.0))
        out[f"{name}_std_reported_max"] = float(np.max(reported)) * (1000.0 if name == "trans" else np.degrees(1.0))
    return out


def _row(name: str, r: dict) -> str:
    return (f"| {name} | {r['runs']} x {r['frames']} | {r['rot_spread_over_std_median']:.2f} "
            f"({r['rot_spread_over_std_range'][0]:.2f}-{r['rot_spread_over_std_range'][1]:.2f}) | "
            f"{r['trans_spread_over_std_median']:.2f} ({r['trans_spread_over_std_range'][0]:.2f}-"
            f"{r['trans_spread_over_std_range'][1]:.2f}) | {r['rot_z_rms']:.2f} / {r['trans_z_rms']:.2f} | "
            f"{r['rot_z_rms_uninflated']:.2f} / {r['trans_z_rms_uninflated']:.2f} | "
            f"{min(r['std_inflation']):.2f}-{max(r['std_inflation']):.2f} | {r['cpu_s_per_run']:.0f} |")


def run(quick: bool = False) -> dict:
    corners = run_mc(4 if quick else 8, 3)
    images = run_mc(2 if quick else 3, 2, images=True)
    results = {"calib_std_z_rms_rot_corners": corners["rot_z_rms"], "calib_std_z_rms_trans_corners": corners["trans_z_rms"],
               "calib_std_z_rms_rot_images": images["rot_z_rms"], "calib_std_z_rms_trans_images": images["trans_z_rms"],
               "calib_std_z_rms_rot_images_uninflated": images["rot_z_rms_uninflated"],
               "calib_std_z_rms_trans_images_uninflated": images["trans_z_rms_uninflated"]}
    lines = ["## Ring calibration: is the per-camera std honest?", "",
             "`calibrate_ring`'s per-camera std (the ring file's `extrinsics_std`) against the errors it should "
             "describe: the simulated lab, the same true rig, rough ring and drive each run (a full turn at each of "
             "the first mapping stations, straight drives between), the noise drawn again per run; no odometry, no "
             "map; each camera's error relative to the others (the std's gauge) in its optical frame. *spread / "
             "std*: the RMS of the errors over the runs over the mean reported std, per camera and axis (median, "
             "range); *z RMS*: RMS of error / std over every camera, axis and run (1 = honest; bias included); "
             "*uninflated*: the same without the inflation for the residuals' frame-to-frame correlation "
             "(`ring_calibration.residual_lag1_correlation`).", "",
             "| corner errors | runs x frames | rotation spread / std | translation spread / std | z RMS rot / trans | "
             "uninflated z RMS rot / trans | inflation | CPU per run (s) |", "|---|---|---|---|---|---|---|---|",
             _row("independent 0.3 px noise", corners), _row("rendered images, detected", images), "",
             f"CPU time (utime+stime) of `calibrate_ring`; load average at the end {os.getloadavg()[0]:.1f} on "
             f"{os.cpu_count()} cores."]
    return {"results": results, "markdown": "\n".join(lines) + "\n"}


if __name__ == "__main__":
    import logging

    logging.basicConfig(level=logging.ERROR)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--stations", type=int, default=3)
    ap.add_argument("--images", action="store_true", help="rendered images through the detector (slow)")
    a = ap.parse_args()
    print(json.dumps(run_mc(a.runs, a.stations, images=a.images), indent=1))
