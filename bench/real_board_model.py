"""Is a board recording's gap to TagSLAM ours or its model's? TagSLAM's board model re-enacted (issue 11).

TagSLAM does not hold a board's tags exactly at its layout: each tag has its own pose, tied to the
board's by a relative prior of the board's ``tag_position_noise`` / ``tag_rotation_noise``
(tagslam.yaml; staggered_board.cpp, ``PoseWithNoise`` per tag), and it publishes the rig poses only
of the frames it used. This script solves one small problem several ways and compares each answer
with TagSLAM's tags (the SE(3) fit of bench_real, over the 4 corners of every common tag):

* the corners of every detection of a board's tag, raw pixels, plain least squares, TagSLAM's
  ``pixel_noise`` (tagslam.yaml; 1 px without it), TagSLAM's extrinsics held fixed, one rig pose per
  frame, one pose per board (the first board with the most detections held as the gauge);
* ``exact``: the tags exactly at the layout (the package's boards);
* ``loose``: each tag's deviation from the layout free, with tagslam.yaml's tag noise as its prior
  (TagSLAM's model; the package's mapping has it since: a loose board, boards.py, which
  ``tagslam_boards`` reads from the same keys, so ``bench_real`` maps tests 13 and 24 with it);
* ``scaled``: exact layouts with one free scale of the layouts' positions (tag sizes kept): the
  pitch / size ratio the detections favour;
* each on every frame, and on the frames TagSLAM has a rig pose for (``--frames tagslam``: TagSLAM's
  frame selection, read from its answer: a diagnosis, not a mapping).

Started from the package's map (``results/bench/real/<test>/map.yaml``, written by
``bench/bench_real.py --only <test>``) or from TagSLAM's (``--init tagslam``): the same optimum from
both says the answer is the model's, not the start's. Levenberg-Marquardt on the sparse normal
equations, the Jacobian by finite differences over columns that share no residual.

``--objective``: TagSLAM's stated problem (loose boards, its pixel_noise, plain least squares) at
TagSLAM's answer (its tags, its rig poses where it has them, the other frames fitted alone; each
board's frame the one that costs its tags' play least, TagSLAM's board poses not being in its
answer), at the package's map (every rig pose fitted alone), and the minima of a full solve from
each: is either answer the optimum of that problem (bench/real_objective.py for the recordings
without boards)? With ``--frames all`` the minimum from the package's map is written to
``results/bench/real/<test>/objective_min.yaml``.

Usage: ``python bench/real_board_model.py test_24 [--init tagslam] [--models exact,loose,scaled]
[--frames all,tagslam] [--objective]``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import yaml  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_real  # noqa: E402
from sparse_lm import levenberg_marquardt  # noqa: E402
from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.evaluation.maps import map_error  # noqa: E402
from aruco_ring_localization.importers import tagslam_boards  # noqa: E402
from aruco_ring_localization.importers.tagslam import tagslam_measurements  # noqa: E402
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap  # noqa: E402
from aruco_ring_localization.markers import marker_corners  # noqa: E402


def tag_noise(tagslam_yaml: str) -> Dict[str, Tuple[float, float]]:
    """Board name -> (tag_position_noise m, tag_rotation_noise rad) of tagslam.yaml's board bodies
    (0 where not given: the tags exact, as TagSLAM's default)."""
    with open(tagslam_yaml, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    out: Dict[str, Tuple[float, float]] = {}
    for entry in doc.get("bodies", []) or []:
        for name, body in (entry or {}).items():
            kind = (body or {}).get("type", "")
            if kind in ("board", "staggered_board"):
                b = body.get(kind, {}) or {}
                out[name] = (float(b.get("tag_position_noise", 0.0)), float(b.get("tag_rotation_noise", 0.0)))
    return out


@dataclass
class Problem:
    """The observations and the starting values (see the module docstring)."""

    tag_ids: List[int]
    board: np.ndarray          # (T,) board index of each tag
    layout: np.ndarray         # (T, 4, 4) T_board_tag
    corners: np.ndarray        # (T, 4, 3) each tag's corners in its own frame
    noise: np.ndarray          # (T, 2) its position (m) and rotation (rad) prior std, 0: exact
    obs_frame: np.ndarray      # (N,)
    obs_tag: np.ndarray        # (N,)
    obs_cam: List[object]      # (N,) the ring camera of each observation
    obs_px: np.ndarray         # (N, 4, 2)
    T_W_base0: np.ndarray      # (F, 4, 4)
    T_W_board0: np.ndarray     # (B, 4, 4)
    gauge: int
    distances: List[Tuple[int, np.ndarray, int, np.ndarray, float, float]]   # (tag a, point, tag b, point, m, std)
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))   # (F,) each frame's stamp, s


def build(test: str, init: str, frames_sel: str,
          measurements: bool = False) -> Tuple[Problem, MarkerMap, object, float]:
    out_dir, src, tags, ref, ring, sizes, ignore, frames, truth = bench_real._load_case(test)
    boards = tagslam_boards(os.path.join(src, "tagslam.yaml"), rig_bodies=(ref.rig_body,))
    if boards is None or not len(boards):
        raise SystemExit(f"real_board_model: {test} declares no boards")
    noise_of = tag_noise(os.path.join(src, "tagslam.yaml"))
    if init == "ours":
        path = os.path.join(out_dir, "map.yaml")
        if not os.path.exists(path):
            raise SystemExit(f"real_board_model: no map {path}: run bench/bench_real.py --only {test} first")
        start = MarkerMap.load(path)
    else:
        start = truth
    tag_ids = [m for m in sorted(truth.ids) if boards.board_of(m) is not None]
    tix = {m: k for k, m in enumerate(tag_ids)}
    board = np.array([boards.board_of(m) for m in tag_ids])
    layout = np.array([boards.boards[b].layout[m] for m, b in zip(tag_ids, board)])
    corners = np.array([marker_corners(sizes(m)) for m in tag_ids])
    noise = np.array([noise_of.get(boards.boards[b].name, (0.0, 0.0)) for b in board])
    keep = None
    if frames_sel == "tagslam":
        keep = {int(round(t * 1e6)) for t in ref.stamps}
    fr = [f for f in frames if (keep is None or int(round(f.stamp * 1e6)) in keep)
          and any(o.marker_id in tix for cf in f.cameras.values() for o in cf.observations)]
    cams = {name: ring[name] for name in ring.names} if hasattr(ring, "names") else {c.name: c for c in ring}
    of, ot, oc, opx = [], [], [], []
    for fi, f in enumerate(fr):
        for name, cf in f.cameras.items():
            for o in cf.observations:
                if o.marker_id in tix:
                    of.append(fi)
                    ot.append(tix[o.marker_id])
                    oc.append(cams[name])
                    opx.append(np.asarray(o.corners, dtype=float).reshape(4, 2))
    obs_frame, obs_tag = np.array(of), np.array(ot)
    T_W_board0 = np.zeros((len(boards.boards), 4, 4))
    for b, B in enumerate(boards.boards):
        ids = [m for m in B.ids if m in start]
        T_W_board0[b] = geo.rigid_fit([B.layout[m][:3, 3] for m in ids], [start.T_map_marker(m)[:3, 3] for m in ids])
    # Each frame's rig pose: PnP over its corners through the starting boards (all its cameras).
    import cv2

    T_W_base0 = np.tile(np.eye(4), (len(fr), 1, 1))
    for fi in range(len(fr)):
        sel = np.flatnonzero(obs_frame == fi)
        c0 = oc[sel[0]]
        on_c0 = [k for k in sel if oc[k] is c0]
        P = np.concatenate([geo.transform_points(T_W_board0[board[obs_tag[k]]] @ layout[obs_tag[k]],
                                                 corners[obs_tag[k]]) for k in on_c0])
        x = np.concatenate([opx[k] for k in on_c0])
        model = c0.model
        _, rv, tv = cv2.solvePnP(P, x, model.K, model.opencv_distortion, flags=cv2.SOLVEPNP_SQPNP)
        _, rv, tv = cv2.solvePnP(P, x, model.K, model.opencv_distortion, rv, tv, True)
        T_cam_W = geo.transform_from_rvec_tvec(rv.ravel(), tv.ravel())
        T_W_base0[fi] = geo.inverse(T_cam_W) @ c0.T_cam_base
    counts = np.bincount(board[obs_tag], minlength=len(boards.boards))
    dist: List[Tuple[int, np.ndarray, int, np.ndarray, float, float]] = []
    if measurements:
        meas = tagslam_measurements(os.path.join(src, "tagslam.yaml"), ignore)
        for d in (meas.distances if meas is not None else []):
            if d.a.marker_id in tix and d.b.marker_id in tix:
                dist.append((tix[d.a.marker_id], d.a.local(sizes(d.a.marker_id)), tix[d.b.marker_id],
                             d.b.local(sizes(d.b.marker_id)), float(d.distance), float(d.std)))
    prob = Problem(tag_ids, board, layout, corners, noise, obs_frame, obs_tag, oc, np.array(opx), T_W_base0,
                   T_W_board0, int(np.argmax(counts)), dist, np.array([f.stamp for f in fr]))
    return prob, truth, sizes, float(tags.pixel_noise or 1.0)


def _exp(v: np.ndarray, T0: np.ndarray) -> np.ndarray:
    T = np.array(T0, copy=True)
    T[..., :3, :3] = Rotation.from_rotvec(v[..., :3].reshape(-1, 3)).as_matrix().reshape(T0[..., :3, :3].shape) \
        @ T0[..., :3, :3]
    T[..., :3, 3] = T0[..., :3, 3] + v[..., 3:]
    return T


class Model:
    """Parameters: 6 per frame, 6 per board but the gauge, 6 per loose tag, 1 layout scale (scaled)."""

    def __init__(self, p: Problem, kind: str, pixel_noise: float):
        self.p, self.kind, self.px = p, kind, pixel_noise
        self.nF, self.nB, self.nT = len(p.T_W_base0), len(p.T_W_board0), len(p.tag_ids)
        self.bvar = [b for b in range(self.nB) if b != p.gauge]
        self.boff = {b: 6 * self.nF + 6 * k for k, b in enumerate(self.bvar)}
        self.loose = np.flatnonzero((p.noise > 0).all(axis=1)) if kind == "loose" else np.zeros(0, dtype=int)
        self.toff = 6 * self.nF + 6 * len(self.bvar)
        self.tpos = {int(t): self.toff + 6 * k for k, t in enumerate(self.loose)}
        self.soff = self.toff + 6 * len(self.loose)
        self.n = self.soff + (1 if kind == "scaled" else 0)
        cams = {id(c): c for c in p.obs_cam}
        self.cam_groups = [(cams[i], np.array([id(c) == i for c in p.obs_cam])) for i in cams]
        self._sparsity()

    def tags(self, x: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """(T_W_base (F, 4, 4), T_W_tag (T, 4, 4)) at ``x``."""
        p = self.p
        Tb = p.T_W_board0.copy()
        Tb[self.bvar] = _exp(x[6 * self.nF:self.toff].reshape(-1, 6), p.T_W_board0[self.bvar])
        lay = p.layout.copy()
        if self.kind == "scaled":
            lay[:, :3, 3] *= 1.0 + x[self.soff]
        if len(self.loose):
            d = x[self.toff:self.soff].reshape(-1, 6)
            D = np.tile(np.eye(4), (len(self.loose), 1, 1))
            D[:, :3, :3] = Rotation.from_rotvec(d[:, :3]).as_matrix()
            D[:, :3, 3] = d[:, 3:]
            lay[self.loose] = lay[self.loose] @ D
        return _exp(x[:6 * self.nF].reshape(-1, 6), p.T_W_base0), Tb[p.board] @ lay

    def residuals(self, x: np.ndarray) -> np.ndarray:
        p = self.p
        Tbase, Tt = self.tags(x)
        out = np.zeros((len(p.obs_frame), 4, 2))
        for cam, sel in self.cam_groups:
            M = cam.T_cam_base @ np.linalg.inv(Tbase[p.obs_frame[sel]]) @ Tt[p.obs_tag[sel]]
            P = np.einsum("nij,nkj->nki", M[:, :3, :3], p.corners[p.obs_tag[sel]]) + M[:, None, :3, 3]
            out[sel] = cam.model.project(P.reshape(-1, 3)).reshape(-1, 4, 2) - p.obs_px[sel]
        r = [out.ravel() / self.px]
        if len(self.loose):
            d = x[self.toff:self.soff].reshape(-1, 6)
            r.append((d[:, :3] / p.noise[self.loose, 1:2]).ravel())
            r.append((d[:, 3:] / p.noise[self.loose, 0:1]).ravel())
        if p.distances:
            r.append(np.array([(np.linalg.norm(Tt[a, :3, :3] @ pa + Tt[a, :3, 3] - Tt[b, :3, :3] @ pb - Tt[b, :3, 3])
                                - dd) / sd for a, pa, b, pb, dd, sd in p.distances]))
        return np.concatenate(r)

    def _sparsity(self) -> None:
        p = self.p
        rows: List[int] = []
        cols: List[int] = []
        for k in range(len(p.obs_frame)):
            cc = list(range(6 * p.obs_frame[k], 6 * p.obs_frame[k] + 6))
            b = int(p.board[p.obs_tag[k]])
            if b in self.boff:
                cc += list(range(self.boff[b], self.boff[b] + 6))
            t = int(p.obs_tag[k])
            if t in self.tpos:
                cc += list(range(self.tpos[t], self.tpos[t] + 6))
            if self.kind == "scaled":
                cc.append(self.soff)
            for r in range(8 * k, 8 * k + 8):
                rows += [r] * len(cc)
                cols += cc
        n8 = 8 * len(p.obs_frame)
        for k, t in enumerate(self.loose):
            for j in range(6):
                rows.append(n8 + (3 * k + j if j < 3 else 3 * len(self.loose) + 3 * k + j - 3))
                cols.append(self.tpos[int(t)] + j)
        self.m = n8 + 6 * len(self.loose)
        for k, (ta, _, tb, _, _, _) in enumerate(p.distances):
            cc = []
            for t in (ta, tb):
                b = int(p.board[t])
                if b in self.boff:
                    cc += list(range(self.boff[b], self.boff[b] + 6))
                if int(t) in self.tpos:
                    cc += list(range(self.tpos[int(t)], self.tpos[int(t)] + 6))
            if self.kind == "scaled":
                cc.append(self.soff)
            for c in sorted(set(cc)):
                rows.append(self.m + k)
                cols.append(c)
        self.m += len(p.distances)
        self.S = sp.csc_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.m, self.n))
        # Columns that share no residual, perturbed together (greedy colouring).
        S = self.S.tocsc()
        used: List[set] = []
        self.groups: List[List[int]] = []
        for c in range(self.n):
            rs = set(S.indices[S.indptr[c]:S.indptr[c + 1]].tolist())
            for g, u in zip(self.groups, used):
                if not (u & rs):
                    g.append(c)
                    u |= rs
                    break
            else:
                self.groups.append([c])
                used.append(set(rs))

    def jacobian(self, x: np.ndarray, r0: np.ndarray, h: float = 1e-7) -> sp.csr_matrix:
        S = self.S
        data, ri, ci = [], [], []
        for g in self.groups:
            dx = np.zeros(self.n)
            dx[g] = h
            dr = (self.residuals(x + dx) - r0) / h
            for c in g:
                rows = S.indices[S.indptr[c]:S.indptr[c + 1]]
                data.append(dr[rows])
                ri.append(rows)
                ci.append(np.full(len(rows), c))
        return sp.csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))), shape=(self.m, self.n))


def solve(model: Model, iterations: int = 50, x0: Optional[np.ndarray] = None,
          free: Optional[np.ndarray] = None) -> Tuple[np.ndarray, float, int]:
    """Levenberg-Marquardt from ``x0`` (zero: the starting values) over the columns ``free`` (all by
    default); (x, cost, iterations)."""
    def jac(x: np.ndarray, r: np.ndarray) -> sp.spmatrix:
        J = model.jacobian(x, r)
        return J if free is None else J.tocsc()[:, free].tocsr()

    return levenberg_marquardt(model.residuals, jac, np.zeros(model.n) if x0 is None else x0, free, iterations,
                               damping=1e-3, rel_tol=1e-9, floor=1e-9)


def x_at(model: Model, T_W_base: np.ndarray, T_W_tag: np.ndarray) -> np.ndarray:
    """The parameters that put the rig at ``T_W_base`` (F, 4, 4) and the tags at ``T_W_tag`` (T, 4, 4)
    (loose model): each board's frame the rigid fit of its layout onto those tags (the gauge board
    stays at its starting pose, so the problem must start from the same map), each tag's deviation
    from it the rest."""
    p = model.p
    x = np.zeros(model.n)
    dR = np.einsum("nij,nkj->nik", T_W_base[:, :3, :3], p.T_W_base0[:, :3, :3])
    x[:6 * model.nF] = np.concatenate([Rotation.from_matrix(dR).as_rotvec(),
                                       T_W_base[:, :3, 3] - p.T_W_base0[:, :3, 3]], axis=1).ravel()
    from scipy.optimize import least_squares

    Tb = p.T_W_board0.copy()
    for b in range(model.nB):
        on = np.flatnonzero(p.board == b)
        T0 = geo.rigid_fit([p.layout[t][:3, 3] for t in on], [T_W_tag[t][:3, 3] for t in on])
        on = [t for t in on if t in model.tpos]

        def play(v, T0=T0, on=on):   # the board's tags' play priors with the board frame at exp(v) T0
            T = _exp(v[None], T0[None])[0]
            D = [geo.inverse(T @ p.layout[t]) @ T_W_tag[t] for t in on]
            return np.concatenate([np.r_[Rotation.from_matrix(d[:3, :3]).as_rotvec() / p.noise[t, 1],
                                         d[:3, 3] / p.noise[t, 0]] for t, d in zip(on, D)])

        # The board frame that costs the tags' play least (the tags held): TagSLAM's board pose is
        # not in its answer.
        Tb[b] = _exp(least_squares(play, np.zeros(6)).x[None], T0[None])[0] if on else T0
        if b == p.gauge:
            p.T_W_board0[b] = Tb[b]
    for b in model.bvar:
        v = np.r_[Rotation.from_matrix(Tb[b][:3, :3] @ p.T_W_board0[b][:3, :3].T).as_rotvec(),
                  Tb[b][:3, 3] - p.T_W_board0[b][:3, 3]]
        x[model.boff[b]:model.boff[b] + 6] = v
    for t in model.loose:
        D = geo.inverse(Tb[p.board[t]] @ p.layout[t]) @ T_W_tag[t]
        x[model.tpos[int(t)]:model.tpos[int(t)] + 6] = np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]]
    return x


def objective(test: str, frames_sel: str, iterations: int = 50) -> None:
    """TagSLAM's stated problem (loose boards, its pixel_noise, plain least squares) evaluated at
    (a) TagSLAM's answer (its tags; its rig poses where it has them, the others fitted alone),
    (b) the package's map (every rig pose fitted alone), (c) the minimum from (a), (d) from (b):
    costs (chi^2 = 2 x the solver's cost) and the map RMS between each pair (bench/real_objective.py
    does the same for the recordings without boards)."""
    t0 = time.process_time()
    answers: Dict[str, Tuple[Model, np.ndarray]] = {}
    for init in ("tagslam", "ours"):
        prob, truth, sizes, px = build(test, init, frames_sel)
        model = Model(prob, "loose", px)
        frame_cols = np.arange(6 * model.nF)
        if init == "tagslam":
            _, ref, _ = _reference(test)
            have = {int(round(t * 1e6)): T for t, T in zip(ref.stamps, ref.T_map_rig)}
            keys = [int(round(s * 1e6)) for s in prob.stamps]
            Tb = np.array([have.get(k, T) for k, T in zip(keys, prob.T_W_base0)])
            lack = np.array([k not in have for k in keys])
            x = x_at(model, Tb, np.array([truth.T_map_marker(m) for m in prob.tag_ids]))
            answers["a"] = (model, x)
            if lack.any():
                cols = (6 * np.flatnonzero(lack)[:, None] + np.arange(6)).ravel()
                x, _, _ = solve(model, iterations, x, cols)
                answers["a"] = (model, x)
            x2, _, _ = solve(model, iterations, x, frame_cols)
            answers["a'"] = (model, x2)
            print(f"  TagSLAM has rig poses for {int((~lack).sum())} of {model.nF} frames", flush=True)
        else:
            ours = MarkerMap.load(os.path.join(bench_real.OUT, test, "map.yaml"))
            x = x_at(model, prob.T_W_base0, np.array([ours.T_map_marker(m) for m in prob.tag_ids]))
            x, _, _ = solve(model, iterations, x, frame_cols)
            answers["b"] = (model, x)
    for key, start in (("c", "a"), ("d", "b")):
        model, x0 = answers[start]
        x, _, its = solve(model, iterations, x0)
        answers[key] = (model, x)
        print(f"  ({key}) full batch from ({start}): {its} iterations ({time.process_time() - t0:.0f} s CPU)", flush=True)
    maps = {}
    names = {"a": "TagSLAM's answer", "a'": "TagSLAM's tags, poses refitted", "b": "the package's map",
             "c": "minimum from (a)", "d": "minimum from (b)"}
    for k, (model, x) in answers.items():
        _, Tt = model.tags(x)
        maps[k] = MarkerMap([MarkerEntry(m, Tt[i], sizes(m)) for i, m in enumerate(model.p.tag_ids)], frame_id="map")
        r = model.residuals(x)
        nc = 8 * len(model.p.obs_frame)
        cc, cp = float(r[:nc] @ r[:nc]), float(r[nc:] @ r[nc:])
        print(f"  ({k}) {names[k]}: {cc + cp:.1f} = corners {cc:.1f} + tag play priors {cp:.1f}; corner RMS "
              f"{float(np.sqrt(2.0 * np.mean(np.square(r[:nc])))) * model.px:.3f} px (per corner); vs TagSLAM "
              f"{map_error(maps[k], truth, best_fit=True)['position_rms_mm']:.2f} mm", flush=True)
    if frames_sel == "all":   # the minimum from the package's map, to compare other maps with it
        maps["d"].save(os.path.join(bench_real.OUT, test, "objective_min.yaml"))
    ks = list(maps)
    print("  map RMS between answers (mm): " + "; ".join(
        f"{p}-{q} {map_error(maps[p], maps[q], best_fit=True)['position_rms_mm']:.2f}"
        for n_, p in enumerate(ks) for q in ks[n_ + 1:]))
    print(f"  {time.process_time() - t0:.0f} s CPU, load {open('/proc/loadavg').read().split()[0]}")


def _reference(test: str):
    out_dir, src, tags, ref, ring, sizes, ignore, frames, truth = bench_real._load_case(test)
    return truth, ref, sizes


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("test")
    ap.add_argument("--init", choices=("ours", "tagslam"), default="ours")
    ap.add_argument("--models", default="exact,loose,scaled")
    ap.add_argument("--frames", default="all,tagslam")
    ap.add_argument("--measurements", action="store_true", help="tagslam.yaml's distance measurements too")
    ap.add_argument("--objective", action="store_true", help="TagSLAM's stated problem (loose boards) at its answer, "
                    "at the package's, and the minima from each (see objective())")
    a = ap.parse_args(argv)
    if a.objective:
        for frames_sel in a.frames.split(","):
            print(f"{a.test}: TagSLAM's objective, frames {frames_sel}", flush=True)
            objective(a.test, frames_sel)
        return 0
    print(f"{a.test}: start from {'the package' if a.init == 'ours' else 'TagSLAM'}'s map; corners in raw px, "
          f"plain least squares{'; its distance measurements' if a.measurements else ''}; against TagSLAM's tags "
          f"(SE(3) fit over all corners)")
    for frames_sel in a.frames.split(","):
        prob, truth, sizes, px = build(a.test, a.init, frames_sel, a.measurements)
        for kind in a.models.split(","):
            t0 = time.process_time()
            model = Model(prob, kind, px)
            x, cost, its = solve(model)
            _, Tt = model.tags(x)
            est = MarkerMap([MarkerEntry(m, Tt[k], sizes(m)) for k, m in enumerate(prob.tag_ids)], frame_id="map")
            err = map_error(est, truth, best_fit=True)
            sim = bench_real._similarity(est, truth)
            rms_px = float(np.sqrt(np.mean(np.square(model.residuals(x)[:8 * len(prob.obs_frame)] * px)) * 2.0))
            extra = f", layout scale {1.0 + x[model.soff]:.4f}" if kind == "scaled" else ""
            print(f"  frames {frames_sel} ({len(prob.T_W_base0)}, {len(prob.obs_frame)} detections), {kind}: map RMS "
                  f"{err['position_rms_mm']:.2f} / max {err['position_max_mm']:.2f} mm, similarity fit "
                  f"{sim['map_sim_rms_mm']:.2f} mm (scale {sim['map_scale']:.4f}); corner RMS {rms_px:.3f} px, cost "
                  f"{cost:.1f}{extra}; {its} iterations, {time.process_time() - t0:.1f} s CPU")
    return 0


if __name__ == "__main__":
    sys.exit(main())
