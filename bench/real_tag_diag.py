"""Why does one tag of a real recording move between mapping settings? (issue 11, diagnostic)

Maps one recording as ``bench/real_map_variants.py`` does, once per variant (same syntax), and for
the tag given prints, per variant: its position error against TagSLAM's (after the SE(3) fit of
the whole map) and, per kept observation of it: the station's stamp, the camera, distance and view
angle (from the adjusted poses), the IPPE pair of the single view (errors px, ambiguity), the
reprojection RMS after the adjustment, where the single view alone would put the tag (its offset
from the adjusted tag along and across the line of sight, mm), the station's offset from TagSLAM's
rig pose at that stamp (mm, in TagSLAM's frame after the map's fit), and the whitened residuals of
the odometry links that touch the station. Nothing is saved.

Usage: ``python bench/real_tag_diag.py test_12 97 default: "thinned:min_station_motion_px=10"``
(the base options bench_real's; ``ODOM=package`` as for real_map_variants.py; ``DIAG_ALL=1`` prints every observation, else a
sample of 40 spread over the stamps).
"""
from __future__ import annotations

import dataclasses
import os
import sys
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial.transform import Rotation

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_real  # noqa: E402
from real_map_variants import build_variant, load_case  # noqa: E402
from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization import mapping as mapping_mod  # noqa: E402
from aruco_ring_localization.evaluation.maps import map_error  # noqa: E402
from aruco_ring_localization.importers import tagslam_boards  # noqa: E402
from aruco_ring_localization.importers.tagslam import tagslam_anchors, tagslam_measurements  # noqa: E402
from aruco_ring_localization.mapping import MapBuilder, MappingOptions  # noqa: E402
from aruco_ring_localization.marker_map import MarkerMap  # noqa: E402


def _odometry_residuals(prob, res) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(station_i, station_j, whitened norm, (K, 2) rotation mrad / translation mm) of every link."""
    odo = prob.odometry
    if odo is None:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros((0, 2))
    T = res.T_W_stations
    wn, raw = [], []
    for i, j, Z, s in zip(odo.station_i, odo.station_j, odo.T_ij, odo.sigma):
        E = geo.inverse(Z) @ geo.inverse(T[i]) @ T[j]
        r = Rotation.from_matrix(E[:3, :3]).as_rotvec()
        wn.append(float(np.linalg.norm(np.r_[r, E[:3, 3]] / s)))
        raw.append((1e3 * np.linalg.norm(r), 1e3 * np.linalg.norm(E[:3, 3])))
    return odo.station_i, odo.station_j, np.array(wn), np.array(raw)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) < 3:
        raise SystemExit(__doc__)
    test, tag = args[0], int(args[1])
    case = load_case(test)
    ref, ring, sizes = case.ref, case.ring, case.sizes
    captured: Dict[str, Any] = {}
    orig_problem = MapBuilder._problem

    def problem(self, init, mids):
        prob = orig_problem(self, init, mids)
        captured.update(init=init, mids=list(mids), prob=prob)
        return prob

    MapBuilder._problem = problem           # type: ignore[assignment]
    orig_adjust = MapBuilder._adjust

    def adjust(prob, mids, opts, boards):
        res = orig_adjust(prob, mids, opts, boards)
        captured["res"] = res
        return res

    MapBuilder._adjust = staticmethod(adjust)  # type: ignore[assignment]
    ref_t = np.asarray(ref.stamps, dtype=float)
    for variant in args[2:]:
        name, _, spec = variant.partition(":")
        t0 = time.process_time()
        b, m, det, err = build_variant(case, spec)
        T_truth_est = err["T_truth_est"]
        init, mids, prob, res = captured["init"], captured["mids"], captured["prob"], captured["res"]
        sts = sorted(init.T_W_stations)
        idx = [i for mm in mids for i in init.marker_obs.get(mm, [])]
        print(f"== {test} {name}: map RMS {err['position_rms_mm']:.2f} mm, tag {tag}: "
              f"{err['per_marker'].get(tag, (float('nan'),))[0]:.1f} mm / "
              f"{err['per_marker'].get(tag, (0, float('nan')))[1]:.2f} deg off TagSLAM's; stations {len(sts)}, "
              f"{time.process_time() - t0:.0f} s CPU", flush=True)
        worst = sorted(err["per_marker"].items(), key=lambda kv: -kv[1][0])[:6]
        print("   worst tags (mm): " + ", ".join(f"{k} {v[0]:.1f}" for k, v in worst))
        if tag not in mids:
            print(f"   tag {tag} not mapped")
            continue
        # The walk against TagSLAM's: station position / rotation offsets by stretches of the recording.
        st_t = np.array([b._station_stamps[x] for x in sts])
        offs = []
        for q, x in enumerate(sts):
            k = int(np.argmin(np.abs(ref_t - st_t[q]))) if len(ref_t) else -1
            if k >= 0 and abs(ref_t[k] - st_t[q]) < 0.02:
                T_ts = T_truth_est @ res.T_W_stations[q]
                dp, dr = geo.pose_distance(T_ts, ref.T_map_rig[k])
                offs.append((st_t[q], 1e3 * dp, float(np.degrees(dr))))
        if offs:
            O = np.array(offs)
            edges = np.linspace(O[0, 0], O[-1, 0] + 1e-6, 13)
            parts = []
            for a, c in zip(edges[:-1], edges[1:]):
                w = (O[:, 0] >= a) & (O[:, 0] < c)
                if np.any(w):
                    parts.append(f"{a - O[0, 0]:.0f}s {np.median(O[w, 1]):.0f}mm/{np.median(O[w, 2]):.2f}deg")
            print("   stations vs TagSLAM's rig (median per twelfth of the recording): " + ", ".join(parts))
        k_tag = mids.index(tag)
        T_W_tag = res.T_W_markers[k_tag]
        si, sj, wn, raw = _odometry_residuals(prob, res)
        print(f"   odometry links {len(wn)}: whitened norm median {np.median(wn):.2f}, p95 "
              f"{np.percentile(wn, 95):.2f}, max {wn.max():.2f}" if len(wn) else "   no odometry links")
        rows: List[tuple] = []
        rel: List[np.ndarray] = []
        cams = list(ring.names)
        for n, i in enumerate(idx):
            o = b._obs[i]
            if o.marker_id != tag:
                continue
            s = sts.index(o.station)
            c = cams.index(o.camera)
            T_W_cam = res.T_W_stations[s] @ res.T_base_cams[c]
            T_cm = geo.inverse(T_W_cam) @ T_W_tag
            d = float(np.linalg.norm(T_cm[:3, 3]))
            view = float(np.degrees(mapping_mod._viewing_angle(T_cm)))
            try:
                cand = mapping_mod._candidates(o.xy, sizes(tag), o.focal)
                errs, amb = list(cand.errors), float(cand.ambiguity)
                # The single view's best pose, put in the world by the adjusted station: where it says
                # the tag is, along and across the line of sight from the adjusted tag.
                T_single = T_W_cam @ cand.T_cam_marker
                delta = T_single[:3, 3] - T_W_tag[:3, 3]
                los = (T_W_tag[:3, 3] - T_W_cam[:3, 3]) / d
                along = float(delta @ los)
                across = float(np.linalg.norm(delta - along * los))
            except Exception as exc:  # noqa: BLE001 - a diagnostic: say what failed and go on
                errs, amb, along, across = [float("nan")], float("nan"), float("nan"), float("nan")
                print(f"   obs {i}: no IPPE pose ({exc})")
            stamp = b._station_stamps[o.station]
            k = int(np.argmin(np.abs(ref_t - stamp))) if len(ref_t) else -1
            if k >= 0 and abs(ref_t[k] - stamp) < 0.02:
                T_ts = T_truth_est @ res.T_W_stations[s]
                st_off = 1e3 * float(np.linalg.norm(T_ts[:3, 3] - ref.T_map_rig[k][:3, 3]))
                # The tag in the station's frame, ours against TagSLAM's (its rig pose, its tag).
                ours = (geo.inverse(res.T_W_stations[s]) @ T_W_tag)[:3, 3]
                theirs = (geo.inverse(ref.T_map_rig[k]) @ ref.tags[tag])[:3, 3] if tag in ref.tags else ours
                st_rot = float(np.degrees(geo.pose_distance(T_ts, ref.T_map_rig[k])[1]))
                rel.append(ours - theirs)
            else:
                st_off, st_rot = float("nan"), float("nan")
            touching = np.where((si == s) | (sj == s))[0]
            links = ",".join(f"{wn[q]:.1f}" for q in touching)
            rows.append((stamp, o.camera, d, view, errs, amb, float(res.per_obs_rms_px[n]), along, across,
                         f"{st_off:.1f} / {st_rot:.2f}",
                         links, b._station_frames[o.station]))
        rows.sort(key=lambda r: (r[0], r[1]))
        print(f"   tag {tag}: {len(rows)} observations at {len({r[0] for r in rows})} stations, "
              f"stamps {rows[0][0]:.2f}-{rows[-1][0]:.2f}" if rows else f"   tag {tag}: no observation")
        if rows:
            along = np.array([r[7] for r in rows])
            rms = np.array([r[6] for r in rows])
            print(f"   single views along the line of sight: median {1e3 * np.nanmedian(along):.1f} mm, "
                  f"mean {1e3 * np.nanmean(along):.1f} mm; reprojection RMS median {np.median(rms):.2f}, "
                  f"max {rms.max():.2f} px")
        if rel:
            R = 1e3 * np.array(rel)
            print(f"   the tag in its stations' frames, ours - TagSLAM's (x, y, z mm): median "
                  f"{np.round(np.median(R, axis=0), 1).tolist()}, first {np.round(R[0], 1).tolist()}, "
                  f"last {np.round(R[-1], 1).tolist()}")
            if tag in ref.tags:
                e = (T_truth_est @ T_W_tag)[:3, 3] - ref.tags[tag][:3, 3]
                print(f"   tag {tag} - TagSLAM's in TagSLAM's frame (mm): {np.round(1e3 * e, 1).tolist()}")
                # Against the map's own uncertainty of the tag (the adjustment's covariance, map axes).
                e_map = geo.inverse(T_truth_est)[:3, :3] @ e
                std = np.asarray(m[tag].position_std, dtype=float)
                print(f"   its map position_std (mm): {np.round(1e3 * std, 1).tolist()}; the error in sigmas: "
                      f"{np.round(e_map / np.maximum(std, 1e-9), 1).tolist()}")
        show = rows if os.environ.get("DIAG_ALL") else [rows[q] for q in
                                                         sorted(set(np.linspace(0, len(rows) - 1, min(40, len(rows)))
                                                                    .astype(int)))]
        print("   stamp          cam   dist m  view deg  ippe px (best, other)  amb   rms px  along mm  across mm  "
              "station-vs-TagSLAM mm/deg  frames  odo links (whitened)")
        for r in show:
            e2 = f"{r[4][1]:.2f}" if len(r[4]) > 1 else "-"
            print(f"   {r[0]:.3f} {r[1]:>5} {r[2]:7.2f} {r[3]:8.1f}  {r[4][0]:6.2f} {e2:>6}  {r[5]:10.3f} {r[6]:7.2f} "
                  f"{1e3 * r[7]:8.1f} {1e3 * r[8]:9.1f} {r[9]:>14} {r[11]:8d}  {r[10]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
