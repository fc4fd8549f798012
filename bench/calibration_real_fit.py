"""Which pose set fits a real recording's detections better: ours (calibrate-ring) or TagSLAM's?

For one calibration (:func:`ring_calibration.calibrate_ring` on a TagSLAM test) and the same
observations (those the calibration's adjustment kept):

* :func:`fixed_camera_fit`: the adjustment redone with the cameras held at given extrinsics (a rigid
  rig; markers and rig poses free): its corner RMS for our calibrated cameras and for TagSLAM's;
* :func:`reference_reprojection`: TagSLAM's whole solution as it is (its tags, rig poses and camera
  poses, nothing re-fitted) reprojected on the frames its rig poses cover, and ours on the same
  observations.

Used by bench_calibration_real.py; run alone: ``python bench/calibration_real_fit.py test_6 [frames] [loss]``.
"""
from __future__ import annotations

import os
import sys
from typing import Dict, Sequence

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.bundle_adjustment import BAOptions, BAProblem, _Model, bundle_adjust  # noqa: E402


def _subproblem(prob: BAProblem, T_W_markers, T_W_stations, T_base_cams, keep=None) -> BAProblem:
    k = np.arange(len(prob.obs_marker)) if keep is None else np.flatnonzero(keep)
    return BAProblem(T_W_markers=np.asarray(T_W_markers), sizes=prob.sizes, T_W_stations=np.asarray(T_W_stations),
                     T_base_cams=np.asarray(T_base_cams), obs_marker=prob.obs_marker[k],
                     obs_station=prob.obs_station[k], obs_camera=prob.obs_camera[k], obs_xy=prob.obs_xy[k],
                     obs_focal=prob.obs_focal[k], fixed_marker=prob.fixed_marker, fixed_station=None,
                     obs_lens=None if prob.obs_lens is None else prob.obs_lens[k])


def corner_errors_px(prob: BAProblem) -> np.ndarray:
    """(N,) RMS over its 4 corners of each observation's reprojection error at the problem's poses, px."""
    model = _Model(prob, BAOptions(pixel_noise=1.0, refine_extrinsics=False))
    r = model.residuals(np.zeros(model.n_params))[: model.n_obs_res].reshape(-1, 8)
    return np.sqrt(np.mean(r ** 2, axis=1))


def fixed_camera_fit(cal, T_base_cams: Sequence[np.ndarray]) -> Dict[str, float]:
    """The calibration's adjustment redone with the cameras fixed at ``T_base_cams`` (rig frame:
    any; only the cameras' poses relative to each other matter): corner RMS / median px."""
    res, prob = cal.ba, cal.ba.problem
    T_base_cams = np.asarray(T_base_cams)
    D = res.T_base_cams[0] @ geo.inverse(T_base_cams[0])     # camera 0 stays where it was
    start = _subproblem(prob, res.T_W_markers, res.T_W_stations @ D, T_base_cams)
    out = bundle_adjust(start, BAOptions(pixel_noise=0.5, refine_extrinsics=False, covariance=False, max_nfev=100))
    e = out.per_obs_rms_px
    return {"rms_px": float(out.rms_px_after), "median_px": float(np.median(e)), "n_obs": int(len(e))}


def reference_reprojection(cal, ref, names: Sequence[str], max_dt: float = 0.002) -> Dict[str, float]:
    """TagSLAM's solution (tags, rig poses at the frames' stamps, camera poses) reprojected on the
    calibration's observations of its tags in the frames its rig poses cover, and ours on the same."""
    res, prob = cal.ba, cal.ba.problem
    mids = list(res.marker_ids)
    st_ref = []
    for t in cal.station_stamps:
        j = int(np.argmin(np.abs(ref.stamps - t))) if len(ref.stamps) else -1
        st_ref.append(ref.T_map_rig[j] if j >= 0 and abs(ref.stamps[j] - t) <= max_dt else None)
    keep = np.array([st_ref[s] is not None and mids[m] in ref.tags
                     for s, m in zip(prob.obs_station, prob.obs_marker)])
    if keep.sum() == 0:
        return {"n_obs": 0}
    T_m = [ref.tags.get(m, np.eye(4)) for m in mids]
    T_s = [T if T is not None else np.eye(4) for T in st_ref]
    T_c = [ref.cameras[c] for c in names]
    e_ref = corner_errors_px(_subproblem(prob, T_m, T_s, T_c, keep))
    e_our = corner_errors_px(_subproblem(prob, res.T_W_markers, res.T_W_stations, res.T_base_cams, keep))
    return {"n_obs": int(keep.sum()), "frames": int(sum(T is not None for T in st_ref)),
            "ref_rms_px": float(np.sqrt(np.mean(e_ref ** 2))), "ref_median_px": float(np.median(e_ref)),
            "our_rms_px": float(np.sqrt(np.mean(e_our ** 2))), "our_median_px": float(np.median(e_our))}


def breakdown(cal, names: Sequence[str]) -> Dict[str, object]:
    """Our solution's corner errors per camera, and how they are spread over frames (a few bad
    frames -- motion blur, rolling shutter -- or all of them a little)."""
    res, prob = cal.ba, cal.ba.problem
    e = corner_errors_px(_subproblem(prob, res.T_W_markers, res.T_W_stations, res.T_base_cams))
    per_cam = {c: float(np.sqrt(np.mean(e[prob.obs_camera == k] ** 2))) for k, c in enumerate(names)}
    per_frame = np.array([np.sqrt(np.mean(e[prob.obs_station == s] ** 2)) for s in np.unique(prob.obs_station)])
    worst = np.sort(e)[::-1]
    return {"per_camera_rms_px": per_cam, "frames_rms_px_p50_p90_p99": [float(np.percentile(per_frame, q))
                                                                        for q in (50, 90, 99)],
            "share_of_squared_error_in_worst_5pct_obs": float(np.sum(worst[: len(e) // 20] ** 2) / np.sum(e ** 2)),
            "obs_over_3px": int(np.sum(e > 3.0)), "n_obs": int(len(e))}


if __name__ == "__main__":
    import json
    import time

    sys.path.insert(0, HERE)
    from bench_calibration_real import calibrate_test

    test = sys.argv[1] if len(sys.argv) > 1 else "test_6"
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 400
    loss = sys.argv[3] if len(sys.argv) > 3 else "huber"
    from aruco_ring_localization.ring_calibration import CalibrationOptions

    c0 = time.process_time()
    r = calibrate_test(test, max_frames=n, options=CalibrationOptions(loss=loss))
    cal, ring, ref = r["cal"], r["ring"], r["ref"]
    names = ring.names
    out = {"test": test, "max_frames": n, "loss": loss, "errs": r["errs"], "rms": r["rms"], "used": r["used"],
           "breakdown": breakdown(cal, names),
           "fit_ours": fixed_camera_fit(cal, [cal.ba.T_base_cams[k] for k in range(len(names))]),
           "fit_tagslam": fixed_camera_fit(cal, [ring[c].T_base_cam for c in names]),
           "reference_as_is": reference_reprojection(cal, ref, names),
           "cpu_s": time.process_time() - c0, "load": os.getloadavg()}
    print(json.dumps(out, indent=1, default=float))
