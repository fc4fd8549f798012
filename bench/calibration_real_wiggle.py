"""Is the gap to TagSLAM's camera poses its per-frame "wiggle"? A re-enactment of its camera model.

TagSLAM's cameras.yaml of tests 5 and 6 gives every camera ``wiggle_rotation: 0.01`` (rad) and
``wiggle_translation: 0.01`` (m): each frame gets its own camera pose, tied to the camera's nominal
pose (the one in reference.bag) by a prior with those sigmas, with a corner noise of 1 px and no
robust loss. This script poses that model on our observations (:func:`wiggle_fit`): one camera pose
per (frame, camera) with a prior around a nominal ring, markers and rig poses free; and finds the
model's nominal ring by alternating (the adjustment with the priors around the nominal, then each
camera's nominal the mean of its per-frame poses: block coordinate descent on the joint problem, whose
nominal optimum given the per-frame poses is their mean). Started from our rigid calibration, does
it walk towards TagSLAM's camera poses?

Run: ``python bench/calibration_real_wiggle.py test_6 [frames] [rounds] [relax]`` (prints JSON).
"""
from __future__ import annotations

import os
import sys
import time
from typing import Dict, List, Sequence

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.bundle_adjustment import BAOptions, BAProblem, bundle_adjust  # noqa: E402


def wiggle_fit(cal, nominal: Sequence[np.ndarray], rot_sigma: float = 0.01, trans_sigma: float = 0.01,
               pixel_noise: float = 1.0, max_nfev: int = 60) -> Dict[str, object]:
    """TagSLAM's wiggle model on the calibration's observations around the ``nominal`` ring (camera 0
    kept where our adjustment has it): per-frame camera poses with priors ``rot_sigma`` (rad),
    ``trans_sigma`` (m); returns the per-frame poses by camera, the corner RMS (px) and the cost
    split into corners and priors (in sigmas squared)."""
    res, prob = cal.ba, cal.ba.problem
    nominal = np.asarray(nominal)
    C = len(nominal)
    D = res.T_base_cams[0] @ geo.inverse(nominal[0])
    pairs, inv = np.unique(prob.obs_station * C + prob.obs_camera, return_inverse=True)
    cams = np.stack([nominal[p % C] for p in pairs])
    sub = BAProblem(T_W_markers=res.T_W_markers, sizes=prob.sizes, T_W_stations=res.T_W_stations @ D,
                    T_base_cams=cams, obs_marker=prob.obs_marker, obs_station=prob.obs_station,
                    obs_camera=inv.astype(int), obs_xy=prob.obs_xy, obs_focal=prob.obs_focal,
                    fixed_marker=prob.fixed_marker, fixed_station=None, obs_lens=prob.obs_lens)
    out = bundle_adjust(sub, BAOptions(pixel_noise=pixel_noise, loss="linear", refine_extrinsics=True,
                                       extrinsics_trans_sigma=trans_sigma,
                                       extrinsics_rot_sigma_deg=float(np.degrees(rot_sigma)),
                                       covariance=False, max_nfev=max_nfev))
    per_cam: Dict[int, List[np.ndarray]] = {}
    prior = 0.0
    for k, p in enumerate(pairs):
        T = out.T_base_cams[k]
        per_cam.setdefault(int(p % C), []).append(T)
        d = geo.inverse(nominal[p % C]) @ T
        w = geo.rotation_angle(d[:3, :3])
        prior += (w / rot_sigma) ** 2 + float(np.sum(((T[:3, 3] - nominal[p % C][:3, 3]) / trans_sigma) ** 2))
    corners = float(np.sum((out.per_obs_rms_px ** 2) * 8) / pixel_noise ** 2)
    return {"per_cam": per_cam, "rms_px": float(out.rms_px_after), "cost_corners": corners, "cost_priors": prior,
            "cost": corners + prior}


def rel_errors(a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> List[tuple]:
    """(mm, deg) of ``T_cam0_camk`` in ``a`` against ``b``, k = 1..C-1."""
    out = []
    for k in range(1, len(a)):
        d = geo.pose_distance(geo.inverse(a[0]) @ a[k], geo.inverse(b[0]) @ b[k])
        out.append((round(1000 * d[0], 2), round(float(np.degrees(d[1])), 3)))
    return out


def relaxed_step(nominal: np.ndarray, mean: np.ndarray, relax: float) -> np.ndarray:
    """``nominal`` moved ``relax`` times its way to ``mean`` (1: onto it; 2: over-relaxed, twice as
    far: the alternation's error shrinks by roughly half a round, so a step of 2 lands near the
    fixed point), on SE(3) as rotation vector and translation."""
    d = geo.inverse(nominal) @ mean
    r, t = geo.rvec_tvec_from_transform(d)
    return nominal @ geo.transform_from_rvec_tvec(relax * np.asarray(r), relax * np.asarray(t))


def walk(cal, start: Sequence[np.ndarray], tagslam: Sequence[np.ndarray], ours: Sequence[np.ndarray], rounds: int,
         relax: float = 1.0) -> List[Dict[str, object]]:
    """The alternation from ``start``: per round the wiggle fit's cost and the nominal ring's
    distance to TagSLAM's and to ours (``relax``: :func:`relaxed_step`)."""
    nominal = [np.asarray(T) for T in start]
    steps = []
    for _ in range(rounds):
        f = wiggle_fit(cal, nominal)
        steps.append({"cost": round(f["cost"], 1), "cost_corners": round(f["cost_corners"], 1),
                      "cost_priors": round(f["cost_priors"], 1), "rms_px": round(f["rms_px"], 4),
                      "vs_tagslam": rel_errors(nominal, tagslam), "vs_ours": rel_errors(nominal, ours)})
        nominal = [relaxed_step(nominal[k], geo.average_transforms(f["per_cam"][k]), relax) if k in f["per_cam"]
                   else nominal[k] for k in range(len(nominal))]
    steps.append({"vs_tagslam": rel_errors(nominal, tagslam), "vs_ours": rel_errors(nominal, ours)})
    return steps


if __name__ == "__main__":
    import json
    import logging

    import bench_calibration_real as bcr

    logging.basicConfig(level=logging.WARNING)
    test = sys.argv[1] if len(sys.argv) > 1 else "test_6"
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 150
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 4
    relax = float(sys.argv[4]) if len(sys.argv) > 4 else 1.0
    bcr.OUT = os.path.join(bcr.ROOT, "results", "bench", "real_calibration_wiggle")
    c0 = time.process_time()
    r = bcr.calibrate_test(test, max_frames=n)
    names = r["ring"].names
    tagslam = [r["ring"][c].T_base_cam for c in names]
    ours = list(r["cal"].ba.T_base_cams)
    out = {"test": test, "frames": r["used"], "rigid_errs": r["errs"],
           "relax": relax, "from_ours": walk(r["cal"], ours, tagslam, ours, rounds, relax),
           "from_tagslam": walk(r["cal"], tagslam, tagslam, ours, 2),
           "cpu_s": time.process_time() - c0, "load": os.getloadavg()}
    for k, v in out.items():
        print(k, json.dumps(v, default=float))
