"""Is TagSLAM's answer the optimum of the problem its own files state, and is ours? (issue 11)

TagSLAM's objective re-enacted as one cost, from the recording's files alone (nothing fitted to the
reference): the 4 corners of every detection, raw pixels, sigma ``tagslam_parameters.pixel_noise``
(tagslam.yaml; 1 px without it); each tag whose pose tagslam.yaml gives, a prior on that pose with
its own noise or the body's ``override_tag_*_noise`` (``TagslamTags.known_noise``, what the importer
reads); the static body held where the file puts it (its 0.1 mm / 1e-5 rad prior); one rig pose per
frame with detections; the rig's odometry (tagslam.yaml's ``odom_topic``, ``T_body_odom`` and its
per-message noise, ``odom_acceleration`` ..., through ``TagslamOdometry.link_noise`` and
``OdometryTrack.links``) between consecutive frames; the cameras held at TagSLAM's poses (the
recordings with two cameras state them at 1e-6 in camera_poses.yaml; a single camera's pose in the
rig is a gauge of the rig poses alone). Plain least squares (TagSLAM uses no robust loss). Cost =
sum of squared whitened residuals (chi^2), split into corners, tag priors and odometry.

Evaluated (a) at TagSLAM's answer (its tags; its rig poses where reference.bag has one, the other
frames' poses optimised alone with the rest held), (a') the same with every rig pose refitted to
TagSLAM's tags, (b) at the package's map (``results/bench/real/<test>/map.yaml``, written by
``bench/bench_real.py --only <test>``; its stations are not in the file: every rig pose refitted to
the map), (c) the minimum of a full batch solve (Levenberg-Marquardt, every tag and rig pose free)
from (a), (d) from (b); the map RMS between each pair (SE(3) fit over the 4 corners of every common
tag, bench_real's).

Left out: TagSLAM's view limits (``minimum_viewing_angle``: its init_pose drops views that are
nearly edge-on; the package keeps them), boards (test_24: bench/real_board_model.py re-enacts those).

Usage: ``python bench/real_objective.py test_10 [--iterations 30]``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Dict, List, Optional, Sequence, Tuple

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_real  # noqa: E402
from sparse_lm import levenberg_marquardt  # noqa: E402
from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.evaluation.maps import map_error  # noqa: E402
from aruco_ring_localization.importers.tagslam import tagslam_odometry  # noqa: E402
from aruco_ring_localization.mapping_odometry import MappingOdometryOptions, OdometryTrack  # noqa: E402
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap  # noqa: E402
from aruco_ring_localization.markers import marker_corners  # noqa: E402


def _exp(v: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """``T0`` moved by ``v`` (rotation vector applied on the left, translation added): (K, 6), (K, 4, 4)."""
    T = np.array(T0, copy=True)
    if len(v):
        T[:, :3, :3] = Rotation.from_rotvec(v[:, :3]).as_matrix() @ T0[:, :3, :3]
        T[:, :3, 3] = T0[:, :3, 3] + v[:, 3:]
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of each rigid transform of (K, 4, 4)."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


class Objective:
    """TagSLAM's stated problem on one recording (module docstring). Parameters: 6 per frame (rig
    pose), then 6 per tag; ``free`` selects which move."""

    def __init__(self, test: str):
        out_dir, src, tags, ref, ring, sizes, ignore, frames, truth = bench_real._load_case(test)
        self.test, self.out_dir, self.src, self.ref, self.truth, self.sizes = test, out_dir, src, ref, truth, sizes
        self.px = float(tags.pixel_noise or 1.0)
        seen = sorted({o.marker_id for f in frames for cf in f.cameras.values() for o in cf.observations
                       if o.marker_id in truth})
        self.tag_ids = seen
        tix = {m: k for k, m in enumerate(seen)}
        self.corners = np.array([marker_corners(sizes(m)) for m in seen])
        cams = {c.name: c for c in ring}
        fr = [f for f in frames if any(o.marker_id in tix for cf in f.cameras.values() for o in cf.observations)]
        self.frames = fr
        self.stamps = np.array([f.stamp for f in fr])
        of, ot, oc, opx = [], [], [], []
        for fi, f in enumerate(fr):
            for name, cf in f.cameras.items():
                for o in cf.observations:
                    if o.marker_id in tix:
                        of.append(fi)
                        ot.append(tix[o.marker_id])
                        oc.append(name)
                        opx.append(np.asarray(o.corners, dtype=float).reshape(4, 2))
        self.obs_frame, self.obs_tag, self.obs_px = np.array(of), np.array(ot), np.array(opx)
        self.cam_groups = [(cams[n], np.array([c == n for c in oc])) for n in sorted(set(oc))]
        # Tag priors: tagslam.yaml's known poses (body frame; the static body at identity, as the
        # recordings declare it) with their noise (the override when the body sets one).
        pri = [(tix[i], T, np.asarray(tags.known_noise[i][0], dtype=float), float(tags.known_noise[i][1]))
               for i, T in tags.known_poses.items() if i in tix and i in tags.known_noise]
        self.prior_tag = np.array([p[0] for p in pri], dtype=int)
        self.prior_T = np.array([p[1] for p in pri]).reshape(-1, 4, 4)
        self.prior_pos_std = np.array([p[2] for p in pri]).reshape(-1, 3)
        self.prior_rot_std = np.array([p[3] for p in pri])
        # Odometry between consecutive frames (TagSLAM gives every frame a rig pose and links them).
        self.links = None
        found = tagslam_odometry(os.path.join(src, "tagslam.yaml"), ref.rig_body)
        if found is not None:
            from aruco_ring_localization.ros.bag_source import read_reference

            opts = MappingOdometryOptions(topic=found.topic, base_to_odom=found.base_to_odom, **found.link_noise())
            with open(os.devnull, "w", encoding="utf-8") as null:
                st, poses, _ = read_reference(bench_real.cached_bag(test, "tag_detections"), topic=found.topic,
                                              out=null)
            track = OdometryTrack(st, poses)
            f = track.links({k: float(t) for k, t in enumerate(self.stamps)}, opts)
            if f is not None:
                self.links = (f.station_i, f.station_j, f.T_ij, f.sigma)
        self.nF, self.nT = len(fr), len(seen)
        self.n = 6 * (self.nF + self.nT)
        self._sparsity()

    # --- the cost -----------------------------------------------------------------------------
    def unpack(self, x: np.ndarray, Tb0: np.ndarray, Tt0: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        return (_exp(x[:6 * self.nF].reshape(-1, 6), Tb0), _exp(x[6 * self.nF:].reshape(-1, 6), Tt0))

    def residuals(self, Tb: np.ndarray, Tt: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(corners, tag priors, odometry), whitened."""
        out = np.zeros((len(self.obs_frame), 4, 2))
        for cam, sel in self.cam_groups:
            M = cam.T_cam_base @ _inv(Tb[self.obs_frame[sel]]) @ Tt[self.obs_tag[sel]]
            P = np.einsum("nij,nkj->nki", M[:, :3, :3], self.corners[self.obs_tag[sel]]) + M[:, None, :3, 3]
            out[sel] = cam.model.project(P.reshape(-1, 3)).reshape(-1, 4, 2) - self.obs_px[sel]
        rc = out.ravel() / self.px
        T = Tt[self.prior_tag]
        dR = np.einsum("nji,njk->nik", self.prior_T[:, :3, :3], T[:, :3, :3])
        rp = np.concatenate([(Rotation.from_matrix(dR).as_rotvec() / self.prior_rot_std[:, None]).ravel(),
                             ((T[:, :3, 3] - self.prior_T[:, :3, 3]) / self.prior_pos_std).ravel()])
        ro = np.zeros(0)
        if self.links is not None:
            i, j, Z, s = self.links
            E = _inv(Z) @ _inv(Tb[i]) @ Tb[j]
            ro = np.concatenate([Rotation.from_matrix(E[:, :3, :3]).as_rotvec(), E[:, :3, 3]], axis=1) / s
            ro = ro.ravel()
        return rc, rp, ro

    def cost(self, Tb: np.ndarray, Tt: np.ndarray) -> Dict[str, float]:
        rc, rp, ro = self.residuals(Tb, Tt)
        c = {"corners": float(rc @ rc), "tag_priors": float(rp @ rp), "odometry": float(ro @ ro)}
        c["total"] = c["corners"] + c["tag_priors"] + c["odometry"]
        c["corner_rms_px"] = float(np.sqrt(2.0 * np.mean(np.square(rc))) * self.px)   # per corner
        return c

    def _sparsity(self) -> None:
        rows: List[np.ndarray] = []
        cols: List[np.ndarray] = []
        n8 = 8 * len(self.obs_frame)
        r8 = np.arange(n8).reshape(-1, 8)
        for k in range(6):
            rows += [r8.ravel(), r8.ravel()]
            cols += [np.repeat(6 * self.obs_frame + k, 8), np.repeat(6 * (self.nF + self.obs_tag) + k, 8)]
        m = n8
        nP = len(self.prior_tag)
        for a in range(3):   # rotation rows (nP, 3), then translation rows (nP, 3)
            for base, off in ((m, 0), (m + 3 * nP, 3)):
                rr = base + np.arange(nP) * 3 + a
                rows += [rr] * 3
                cols += [6 * (self.nF + self.prior_tag) + off + c for c in range(3)]
        m += 6 * nP
        if self.links is not None:
            i, j, _, _ = self.links
            for a in range(6):
                rr = m + np.arange(len(i)) * 6 + a
                for c in range(6):
                    rows += [rr, rr]
                    cols += [6 * i + c, 6 * j + c]
            m += 6 * len(i)
        self.m = m
        self.S = sp.csc_matrix((np.ones(sum(len(r) for r in rows)), (np.concatenate(rows), np.concatenate(cols))),
                               shape=(self.m, self.n))
        self.S.data[:] = 1.0

    def _groups(self, free: np.ndarray) -> List[np.ndarray]:
        """Free columns that share no residual row, perturbed together (greedy colouring)."""
        S = self.S.tocsc()
        R = S[:, free].T.tocsr()           # (free, rows)
        G = (R @ R.T).tocsr()              # column adjacency
        colour = -np.ones(len(free), dtype=int)
        for c in range(len(free)):
            nb = G.indices[G.indptr[c]:G.indptr[c + 1]]
            taken = set(colour[nb].tolist())
            k = 0
            while k in taken:
                k += 1
            colour[c] = k
        return [free[colour == k] for k in range(colour.max() + 1)]

    def solve(self, Tb0: np.ndarray, Tt0: np.ndarray, free: np.ndarray, iterations: int = 30,
              h: float = 1e-7) -> Tuple[np.ndarray, np.ndarray, int]:
        """Levenberg-Marquardt over the columns ``free`` from (Tb0, Tt0); (Tb, Tt, iterations)."""
        groups = self._groups(free)
        S = self.S.tocsc()
        fpos = -np.ones(self.n, dtype=int)
        fpos[free] = np.arange(len(free))

        def res(xx):
            return np.concatenate(self.residuals(*self.unpack(xx, Tb0, Tt0)))

        def jac(xx, r):   # forward differences, one residual evaluation per group of columns
            data, ri, ci = [], [], []
            for g in groups:
                dx = np.zeros(self.n)
                dx[g] = h
                dr = (res(xx + dx) - r) / h
                for c in g:
                    rows = S.indices[S.indptr[c]:S.indptr[c + 1]]
                    data.append(dr[rows])
                    ri.append(rows)
                    ci.append(np.full(len(rows), fpos[c]))
            return sp.csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))),
                                 shape=(self.m, len(free)))

        x, _, it = levenberg_marquardt(res, jac, np.zeros(self.n), free, iterations, damping=1e-4, rel_tol=1e-7,
                                       floor=1e-12)
        Tb, Tt = self.unpack(x, Tb0, Tt0)
        return Tb, Tt, it

    # --- starts -------------------------------------------------------------------------------
    def frame_cols(self, idx: np.ndarray) -> np.ndarray:
        return (6 * np.asarray(idx, dtype=int)[:, None] + np.arange(6)).ravel()

    def all_cols(self) -> np.ndarray:
        return np.arange(self.n)

    def tags_of(self, m: MarkerMap) -> np.ndarray:
        return np.array([m.T_map_marker(i) for i in self.tag_ids])

    def pnp_poses(self, Tt: np.ndarray) -> np.ndarray:
        """Each frame's rig pose from its corners through the tags ``Tt`` (the first camera's PnP)."""
        import cv2

        Tb = np.tile(np.eye(4), (self.nF, 1, 1))
        for fi in range(self.nF):
            for cam, sel in self.cam_groups:
                k = np.flatnonzero(sel & (self.obs_frame == fi))
                if not len(k):
                    continue
                P = np.concatenate([geo.transform_points(Tt[self.obs_tag[q]], self.corners[self.obs_tag[q]])
                                    for q in k])
                x = self.obs_px[k].reshape(-1, 2)
                _, rv, tv = cv2.solvePnP(P, x, cam.model.K, cam.model.opencv_distortion, flags=cv2.SOLVEPNP_SQPNP)
                _, rv, tv = cv2.solvePnP(P, x, cam.model.K, cam.model.opencv_distortion, rv, tv, True)
                Tb[fi] = geo.inverse(geo.transform_from_rvec_tvec(rv.ravel(), tv.ravel())) @ cam.T_cam_base
                break
        return Tb

    def as_map(self, Tt: np.ndarray) -> MarkerMap:
        return MarkerMap([MarkerEntry(m, Tt[k], self.sizes(m)) for k, m in enumerate(self.tag_ids)], frame_id="map")


def rms(A: MarkerMap, B: MarkerMap) -> float:
    return float(map_error(A, B, best_fit=True)["position_rms_mm"])


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("test")
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--save", action="store_true", help="write the minimum from the package's map, (d), to "
                    "results/bench/real/<test>/objective_min.yaml (to compare other maps with it)")
    a = ap.parse_args(argv)
    t0 = time.process_time()
    ob = Objective(a.test)
    path = os.path.join(ob.out_dir, "map.yaml")
    if not os.path.exists(path):
        raise SystemExit(f"real_objective: no map {path}: run bench/bench_real.py --only {a.test} first")
    ours = MarkerMap.load(path)
    missing = [i for i in ob.tag_ids if i not in ours]
    if missing:
        raise SystemExit(f"real_objective: the package's map lacks tags {missing}")
    print(f"{a.test}: {ob.nF} frames, {ob.nT} tags, {len(ob.obs_frame)} detections, {len(ob.prior_tag)} tag priors, "
          f"{0 if ob.links is None else len(ob.links[0])} odometry links; pixel_noise {ob.px} px "
          f"(setup {time.process_time() - t0:.0f} s CPU)", flush=True)
    # (a) TagSLAM's answer: its tags, its rig poses where it has them, the others optimised alone.
    Tt_a = ob.tags_of(ob.truth)
    ref = {int(round(t * 1e6)): T for t, T in zip(ob.ref.stamps, ob.ref.T_map_rig)}
    have = np.array([int(round(t * 1e6)) in ref for t in ob.stamps])
    Tb_pnp = ob.pnp_poses(Tt_a)
    Tb_a = np.array([ref[int(round(t * 1e6))] if h else T for t, h, T in zip(ob.stamps, have, Tb_pnp)])
    lack = np.flatnonzero(~have)
    if len(lack):
        Tb_a, _, _ = ob.solve(Tb_a, Tt_a, ob.frame_cols(lack), a.iterations)
    answers: Dict[str, Tuple[np.ndarray, np.ndarray]] = {"a": (Tb_a, Tt_a)}
    # (a') TagSLAM's tags, every rig pose refitted.
    Tb_a2, _, _ = ob.solve(Tb_a, Tt_a, ob.frame_cols(np.arange(ob.nF)), a.iterations)
    answers["a'"] = (Tb_a2, Tt_a)
    # (b) the package's map, every rig pose refitted.
    Tt_b = ob.tags_of(ours)
    Tb_b, _, _ = ob.solve(ob.pnp_poses(Tt_b), Tt_b, ob.frame_cols(np.arange(ob.nF)), a.iterations)
    answers["b"] = (Tb_b, Tt_b)
    print(f"  TagSLAM has rig poses for {int(have.sum())} of {ob.nF} frames "
          f"({time.process_time() - t0:.0f} s CPU)", flush=True)
    for key, start in (("c", "a"), ("d", "b")):
        Tb, Tt, its = ob.solve(*answers[start], ob.all_cols(), a.iterations)
        answers[key] = (Tb, Tt)
        print(f"  ({key}) full batch from ({start}): {its} iterations ({time.process_time() - t0:.0f} s CPU)",
              flush=True)
    maps = {k: ob.as_map(v[1]) for k, v in answers.items()}
    names = {"a": "TagSLAM's answer", "a'": "TagSLAM's tags, poses refitted", "b": "the package's map",
             "c": "minimum from (a)", "d": "minimum from (b)"}
    print("  answer: cost total = corners + tag priors + odometry (chi^2); corner RMS px; map RMS vs TagSLAM's tags mm")
    for k, (Tb, Tt) in answers.items():
        c = ob.cost(Tb, Tt)
        print(f"  ({k}) {names[k]}: {c['total']:.1f} = {c['corners']:.1f} + {c['tag_priors']:.1f} + "
              f"{c['odometry']:.1f}; {c['corner_rms_px']:.3f} px; vs TagSLAM {rms(maps[k], ob.truth):.2f} mm", flush=True)
    if a.save:
        maps["d"].save(os.path.join(ob.out_dir, "objective_min.yaml"))
    keys = list(maps)
    print("  map RMS between answers (mm): " + "; ".join(
        f"{p}-{q} {rms(maps[p], maps[q]):.2f}" for n_, p in enumerate(keys) for q in keys[n_ + 1:]))
    print(f"  {time.process_time() - t0:.0f} s CPU, load {open('/proc/loadavg').read().split()[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
