"""Where does our ring calibration differ from TagSLAM's on tests 5 / 6, and does TagSLAM's data selection explain it?

For one recording (``python bench/calibration_real_diag.py test_6 [frames]``), prints JSON:

* ``axes``: each camera's error against TagSLAM's (``T_cam0_camk``) split by axis: rotation (deg) and
  translation (mm) about / along camera k's optical axes (x right, y down, z forward), and the
  translation in camera 0's frame;
* ``view``: the viewing angles of our observations (the angle between the line of sight to the
  marker's centre and the marker's plane: 90 deg face-on), from the adjustment's solution:
  how many fall below TagSLAM's ``minimum_viewing_angle`` of these tests (12 deg; TagSLAM drops
  such detections, init_pose.cpp), and how many are ambiguous in TagSLAM's sense (viewed more
  obliquely than 60 deg from the plane and an IPPE error ratio above 0.3: TagSLAM drops them too);
* ``filtered``: the calibration redone without those observations (frames filtered before
  :func:`ring_calibration.calibrate_ring`): does TagSLAM's selection move our answer towards its?

``python bench/calibration_real_diag.py test_6 400 halves [parts]``: :func:`halves`, our calibration
on consecutive parts of the recording, compared with each other and with TagSLAM's.

No fitting to the reference: TagSLAM's poses are used only as the rough ring's centre and for
the comparison, as in bench_calibration_real.py.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from typing import Dict, List

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.detections import CameraFrame, RingFrame  # noqa: E402
from aruco_ring_localization.pnp import solve_marker_ippe_undistorted  # noqa: E402

TAGSLAM_MIN_VIEW_DEG = 12.0          # tests 5, 6, 8: tagslam.yaml minimum_viewing_angle
TAGSLAM_AMBIGUITY_VIEW_DEG = 60.0    # TagSLAM's default ambiguity_angle_threshold
TAGSLAM_AMBIGUITY_RATIO = 0.3        # TagSLAM's default max_ambiguity_ratio


def axis_errors(ref, est, names: List[str]) -> Dict[str, Dict[str, List[float]]]:
    """Per camera k >= 1: the error of ``T_cam0_camk`` (est against ref) as the rotation vector
    (deg) and translation (mm) of ``ref_rel^-1 est_rel`` (in camera k's optical axes) and the
    position error in camera 0's frame (mm)."""
    out = {}
    c0 = names[0]
    for c in names[1:]:
        ref_rel = geo.inverse(ref[c0]) @ ref[c]
        est_rel = geo.inverse(est[c0]) @ est[c]
        d = geo.inverse(ref_rel) @ est_rel
        r, t = geo.rvec_tvec_from_transform(d)
        out[c] = {"rot_deg_in_camk": [round(float(np.degrees(v)), 4) for v in r],
                  "trans_mm_in_camk": [round(1000 * float(v), 2) for v in t],
                  "pos_mm_in_cam0": [round(1000 * float(v), 2) for v in est_rel[:3, 3] - ref_rel[:3, 3]],
                  "baseline_m": round(float(np.linalg.norm(ref_rel[:3, 3])), 3)}
    return out


def view_angle_deg(T_cam_marker: np.ndarray) -> float:
    """Angle between the line of sight to the marker's centre and the marker's plane, deg (90 = face-on)."""
    ray = T_cam_marker[:3, 3] / np.linalg.norm(T_cam_marker[:3, 3])
    n = T_cam_marker[:3, 2]
    return float(np.degrees(np.arcsin(min(1.0, abs(float(ray @ n))))))


def classify(frames, ring, sizes) -> Dict[tuple, str]:
    """{(frame index, camera, marker id): reason} for the detections TagSLAM would drop."""
    drop = {}
    for k, f in enumerate(frames):
        for name, cf in f.cameras.items():
            model = cf.model or ring[name].model
            focal = np.array([model.fx, model.fy])
            for o in cf.observations:
                xy = model.normalize(o.corners)
                try:
                    cand = solve_marker_ippe_undistorted(xy, sizes(o.marker_id), focal, mirror=True)
                except Exception:       # noqa: BLE001 - a diagnostic: unsolvable ones are counted apart
                    drop[(k, name, o.marker_id)] = "unsolved"
                    continue
                va = view_angle_deg(cand.T_cam_marker)
                if va < TAGSLAM_MIN_VIEW_DEG:
                    drop[(k, name, o.marker_id)] = "view"
                elif va < TAGSLAM_AMBIGUITY_VIEW_DEG and cand.ambiguity > TAGSLAM_AMBIGUITY_RATIO:
                    drop[(k, name, o.marker_id)] = "ambiguous"
    return drop


def filtered_frames(frames, drop: Dict[tuple, str], reasons) -> list:
    out = []
    for k, f in enumerate(frames):
        cams = {}
        for name, cf in f.cameras.items():
            obs = [o for o in cf.observations if drop.get((k, name, o.marker_id)) not in reasons]
            cams[name] = CameraFrame(cf.camera, cf.stamp, obs, cf.model)
        out.append(RingFrame(f.stamp, cams, list(f.missing)))
    return out


def main(test: str, n: int) -> dict:
    import bench_calibration_real as bcr

    from aruco_ring_localization.ring_calibration import CalibrationOptions, calibrate_ring
    from aruco_ring_localization.simulation.calibration_run import rough_ring

    ring, tags, _, frames = bcr.load_case(test, os.path.join(bcr.ROOT, "results", "bench", "real_calibration_diag", test))
    names = ring.names
    sizes = tags.marker_sizes()
    rough = rough_ring(ring, seed=5)
    ref_T = {c: ring[c].T_base_cam for c in names}
    drop = classify(frames, ring, sizes)
    n_obs = sum(len(cf.observations) for f in frames for cf in f.cameras.values())
    counts = {r: sum(1 for v in drop.values() if v == r) for r in ("view", "ambiguous", "unsolved")}
    res = {"test": test, "frames": len(frames), "max_frames": n, "observations": n_obs, "tagslam_drops": counts}
    variants = [("all", ()), ("no_view", ("view",)), ("no_view_no_ambiguous", ("view", "ambiguous", "unsolved"))]
    for label, reasons in variants:
        fr = frames if not reasons else filtered_frames(frames, drop, reasons)
        c0 = time.process_time()
        cal = calibrate_ring(fr, rough, sizes, options=replace(CalibrationOptions(), max_frames=n))
        est = {c: cal.ring[c].T_base_cam for c in names}
        e = bcr.relative_errors(ring, cal.ring, names[0])
        res[label] = {"errs": {c: [round(v[0], 2), round(v[1], 3)] for c, v in e.items()},
                      "axes": axis_errors(ref_T, est, names), "rms_px": round(cal.rms_px_after, 4),
                      "used": cal.frames_used, "cpu_s": round(time.process_time() - c0, 1)}
        sys.stderr.write(f"[diag] {test} {label}: {res[label]['errs']}\n")
    res["load"] = os.getloadavg()
    return res


def halves(test: str, n: int, parts: int = 2) -> dict:
    """Our calibration on each of ``parts`` consecutive parts of the recording (``n`` frames at most
    each): how far apart the recording's own parts put a rigid ring (``T_cam0_camk``, worst camera,
    mm / deg, every pair of parts), against TagSLAM's; the reproducibility a rigid ring has on it."""
    import bench_calibration_real as bcr

    from aruco_ring_localization.ring_calibration import CalibrationOptions, calibrate_ring
    from aruco_ring_localization.simulation.calibration_run import rough_ring

    ring, tags, _, frames = bcr.load_case(test, os.path.join(bcr.ROOT, "results", "bench", "real_calibration_diag", test))
    names = ring.names
    frames = sorted((f for f in frames if f.observation_count() > 0), key=lambda f: f.stamp)
    bounds = np.linspace(0, len(frames), parts + 1).round().astype(int)
    rings = []
    out: dict = {"test": test, "frames": len(frames), "parts": []}
    for a, b in zip(bounds[:-1], bounds[1:]):
        cal = calibrate_ring(frames[a:b], rough_ring(ring, seed=5), tags.marker_sizes(),
                             options=replace(CalibrationOptions(), max_frames=n))
        rings.append(cal.ring)
        e = bcr.relative_errors(ring, cal.ring, names[0])
        std = {c: [round(1000 * float(np.max(cal.std[c][3:])), 3), round(float(np.degrees(np.max(cal.std[c][:3]))), 4)]
               for c in names}
        out["parts"].append({"frames": [int(a), int(b)], "used": cal.frames_used, "rms_px": round(cal.rms_px_after, 4),
                             "camera_frames": cal.camera_frames, "std_mm_deg": std,
                             "vs_tagslam": {c: [round(v[0], 2), round(v[1], 3)] for c, v in e.items()}})
        sys.stderr.write(f"[halves] {test} {a}-{b}: {out['parts'][-1]['vs_tagslam']}\n")
    pairs = {}
    for i in range(len(rings)):
        for j in range(i + 1, len(rings)):
            e = bcr.relative_errors(rings[i], rings[j], names[0])
            pairs[f"{i}-{j}"] = {c: [round(v[0], 2), round(v[1], 3)] for c, v in e.items()}
    out["between_parts"] = pairs
    out["load"] = os.getloadavg()
    return out


if __name__ == "__main__":
    import json
    import logging

    logging.basicConfig(level=logging.ERROR)
    t = sys.argv[1] if len(sys.argv) > 1 else "test_6"
    m = int(sys.argv[2]) if len(sys.argv) > 2 else 400
    if len(sys.argv) > 3 and sys.argv[3] == "halves":
        print(json.dumps(halves(t, m, int(sys.argv[4]) if len(sys.argv) > 4 else 2), indent=1, default=float))
    else:
        print(json.dumps(main(t, m), indent=1, default=float))
