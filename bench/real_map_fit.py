"""Which map fits a recording's detections better: the package's or TagSLAM's? (issue 11)

For a TagSLAM test recording, every ``--step``-th ring frame that has a TagSLAM rig pose is
reprojected through each map: TagSLAM's map with TagSLAM's rig poses as they are, then each map with
the rig pose refitted to that frame (Levenberg-Marquardt over the frame's corners, plain least
squares, started from TagSLAM's pose brought into the map's frame by the maps' best-fit alignment),
our map with its refined extrinsics and with TagSLAM's. Only the tags both maps have count. Printed:
corner reprojection RMS, the median of the frames' RMS and the RMS of the best 99 % of corners (px).
``--scales``: TagSLAM's map and ours scaled about their centre (tag sizes kept): the scale the
detections favour, given the tag sizes.

Usage: ``python bench/real_map_fit.py test_13 [--map results/bench/real/test_13/map.yaml] [--step 1]
[--scales 0.998,1.002]`` (run ``bench/bench_real.py --only test_13`` first: it writes the map).
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Dict, List, Optional, Sequence, Tuple

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_real  # noqa: E402
from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.evaluation.maps import map_error  # noqa: E402
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap  # noqa: E402
from aruco_ring_localization.ring import apply_refined_extrinsics  # noqa: E402


def _views(frames, m: MarkerMap, ids: set, step: int, stamps: Dict[int, np.ndarray]):
    """Per frame with a reference pose: (stamp key, [(camera, (4, 3) corners in the map, (4, 2) px)])."""
    out = []
    for f in frames[::step]:
        k = int(round(f.stamp * 1e6))
        if k not in stamps:
            continue
        views = [(c, m.corners(o.marker_id), np.asarray(o.corners, dtype=float))
                 for c, cf in f.cameras.items() for o in cf.observations if o.marker_id in ids]
        if views:
            out.append((k, views))
    return out


def _residuals(ring, T_map_base: np.ndarray, views) -> np.ndarray:
    r = []
    for c, P, px in views:
        cam = ring[c]
        T = cam.T_cam_base @ geo.inverse(T_map_base)
        r.append(cam.model.project(P @ T[:3, :3].T + T[:3, 3]) - px)
    return np.concatenate(r).ravel()


def reprojection(ring, m: MarkerMap, frames, poses: Dict[int, np.ndarray], ids: set, step: int = 1,
                 T_ref_map: Optional[np.ndarray] = None, refit: bool = True) -> Dict[str, float]:
    """Reprojection of ``m``'s tags ``ids`` over the frames with a pose in ``poses`` (TagSLAM's rig
    poses, its map frame; ``T_ref_map``: our map in that frame), refitted per frame or not (px)."""
    T_map_ref = geo.inverse(T_ref_map) if T_ref_map is not None else np.eye(4)
    errs: List[np.ndarray] = []
    frame_rms: List[float] = []
    for k, views in _views(frames, m, ids, step, poses):
        T0 = T_map_ref @ poses[k]
        if refit:
            x0 = np.concatenate(geo.rvec_tvec_from_transform(T0))
            sol = least_squares(lambda x: _residuals(ring, geo.transform_from_rvec_tvec(x[:3], x[3:]), views),
                                x0, method="lm")
            r = sol.fun
        else:
            r = _residuals(ring, T0, views)
        e = np.hypot(*r.reshape(-1, 2).T)
        errs.append(e)
        frame_rms.append(float(np.sqrt(np.mean(e * e))))
    e = np.concatenate(errs) if errs else np.zeros(0)
    if not e.size:
        return {"frames": 0, "corners": 0, "rms_px": float("nan"), "frame_median_px": float("nan"),
                "rms99_px": float("nan")}
    best = np.sort(e)[:max(1, int(0.99 * e.size))]
    return {"frames": len(frame_rms), "corners": int(e.size), "rms_px": float(np.sqrt(np.mean(e * e))),
            "frame_median_px": float(np.median(frame_rms)), "rms99_px": float(np.sqrt(np.mean(best * best)))}


def scaled(m: MarkerMap, s: float) -> MarkerMap:
    """``m`` with every tag's position moved by the factor ``s`` about the tags' centre (sizes and
    orientations kept)."""
    c = np.mean([m.T_map_marker(i)[:3, 3] for i in m.ids], axis=0)
    out = []
    for e in m:
        T = e.T_map_marker.copy()
        T[:3, 3] = c + s * (T[:3, 3] - c)
        out.append(MarkerEntry(e.marker_id, T, e.size))
    return MarkerMap(out, frame_id=m.frame_id)


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("test")
    p.add_argument("--map", default="", help="our map (default: results/bench/real/<test>/map.yaml)")
    p.add_argument("--step", type=int, default=1, help="every n-th frame")
    p.add_argument("--scales", default="", help="comma-separated factors to scale both maps by")
    a = p.parse_args(argv)
    path = a.map or os.path.join(bench_real.OUT, a.test, "map.yaml")
    if not os.path.exists(path):
        sys.stderr.write(f"real_map_fit: no map {path}: run bench/bench_real.py --only {a.test} first\n")
        return 2
    _, _, _, ref, ring, _, _, frames, truth = bench_real._load_case(a.test)
    ours = MarkerMap.load(path)
    ids = set(ours.ids) & set(truth.ids)
    poses = {int(round(t * 1e6)): T for t, T in zip(ref.stamps, ref.T_map_rig)}
    T_ref_ours = map_error(ours, truth, best_fit=True)["T_truth_est"]
    own_ring = apply_refined_extrinsics(ring, ours.ring_extrinsics, ours.ring_base_frame) \
        if ours.ring_extrinsics else ring
    runs: List[Tuple[str, dict]] = [
        ("TagSLAM's map, TagSLAM's rig poses", dict(ring=ring, m=truth, refit=False)),
        ("TagSLAM's map, poses refitted", dict(ring=ring, m=truth)),
        (f"our map ({'refined' if ours.ring_extrinsics else 'the ring file'} extrinsics), poses refitted",
         dict(ring=own_ring, m=ours, T_ref_map=T_ref_ours))]
    if ours.ring_extrinsics:
        runs.append(("our map with TagSLAM's extrinsics, poses refitted", dict(ring=ring, m=ours, T_ref_map=T_ref_ours)))
    for s in [float(v) for v in a.scales.split(",") if v.strip()]:
        runs.append((f"TagSLAM's map scaled by {s:g}, poses refitted", dict(ring=ring, m=scaled(truth, s))))
        runs.append((f"our map scaled by {s:g}, poses refitted", dict(ring=own_ring, m=scaled(ours, s),
                                                                        T_ref_map=T_ref_ours)))
    print(f"{a.test}: {len(ids)} tags in both maps; frames with a TagSLAM rig pose, one in {a.step}")
    for name, kw in runs:
        r = reprojection(frames=frames, poses=poses, ids=ids, step=a.step, **kw)
        print(f"  {name}: {r['frames']} frames, {r['corners']} corners: RMS {r['rms_px']:.3f} px, frame median "
              f"{r['frame_median_px']:.3f} px, best 99 % {r['rms99_px']:.3f} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())
