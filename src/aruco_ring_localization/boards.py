"""Boards of markers: several markers printed on one board with a known layout (rigid, or each marker with a play).

A board is a rigid body whose markers sit at known poses ``T_board_marker`` (its layout, e.g. a
grid: TagSLAM's ``board`` and ``staggered_board`` bodies, :func:`importers.tagslam_boards`). Given
to the mapping (``MapBuilder(boards=...)``), a board is one unknown of the bundle adjustment instead
of one per marker: every corner of every marker on it observes the board's pose through the layout.
What it brings, as TagSLAM's boards do:

* markers seen only at grazing angles, or only from one viewpoint with an unresolved IPPE
  ambiguity, are held by the others on their board (a mirrored single-marker pose cannot survive
  when the board's other markers fix the plane);
* markers of the board that are never detected, or whose views do not fit, are still placed (from
  the layout), flagged by ``observations: 0`` in the map;
* the map's shape inherits the layout's accuracy (a printed board is better than a walk of
  single-camera views).

By default the layout is taken as exact. A board declared with a play (``tag_position_std`` m /
``tag_rotation_std_deg``, TagSLAM's ``tag_position_noise`` / ``tag_rotation_noise``: ~1 mm / 1 mrad
between a tag and its board) is mapped **loose**: each of its markers is its own unknown, tied to
an unknown board frame (an extra pose with no observations) by a prior of that std on its layout
pose (:func:`loose_priors`, ``MarkerPriors.relative_marker``): a printed board whose tags are off
their nominal grid by a millimetre is mapped as it is, not as it was designed.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .errors import GeometryError
from .markers import marker_corners


@dataclass(frozen=True)
class Board:
    """One board: ``layout`` maps each marker id on it to ``T_board_marker`` (4x4, m).

    ``tag_position_std`` (m, per axis) / ``tag_rotation_std_deg`` (per axis): the play of each
    marker about its layout pose; both 0 (default): a rigid board, one unknown of the adjustment;
    both > 0: a loose board (the module's docstring).
    """

    name: str
    layout: Dict[int, np.ndarray]
    tag_position_std: float = 0.0
    tag_rotation_std_deg: float = 0.0

    def __post_init__(self) -> None:
        p, r = float(self.tag_position_std), float(self.tag_rotation_std_deg)
        if not (p >= 0 and r >= 0 and np.isfinite(p) and np.isfinite(r)) or (p > 0) != (r > 0):
            raise GeometryError(f"board {self.name!r}: tag_position_std and tag_rotation_std_deg must be both 0 "
                                f"(rigid) or both > 0 (loose), got {self.tag_position_std!r} and "
                                f"{self.tag_rotation_std_deg!r}")

    @property
    def ids(self) -> List[int]:
        return sorted(self.layout)

    @property
    def loose(self) -> bool:
        """Whether its markers play about the layout (both stds > 0)."""
        return self.tag_position_std > 0


@dataclass
class BoardSet:
    """Boards of a mapping; a marker belongs to one board at most.

    Attributes:
        boards: the boards.
        source: where they were read (for messages).
    """

    boards: List[Board] = field(default_factory=list)
    source: str = ""

    def __post_init__(self) -> None:
        self._of: Dict[int, int] = {}
        for k, b in enumerate(self.boards):
            for m in b.layout:
                if m in self._of:
                    raise GeometryError(f"boards ({self.source or 'boards'}): marker {m} is on board "
                                        f"{self.boards[self._of[m]].name!r} and on board {b.name!r}")
                self._of[m] = k

    def __len__(self) -> int:
        return len(self.boards)

    def board_of(self, marker_id: int) -> Optional[int]:
        """Index of the board holding ``marker_id``, None when it is on none."""
        return self._of.get(int(marker_id))

    def without(self, names: Sequence[str]) -> "BoardSet":
        drop = set(names)
        return BoardSet([b for b in self.boards if b.name not in drop], self.source)

    def rigid(self) -> "BoardSet":
        """The rigid boards only."""
        return BoardSet([b for b in self.boards if not b.loose], self.source)

    def loose(self) -> "BoardSet":
        """The loose boards only."""
        return BoardSet([b for b in self.boards if b.loose], self.source)


def grid_board(name: str, start_id: int, rows: int, columns: int, size: float, spacing: float,
               staggered: bool = False, T_board_body: Optional[np.ndarray] = None) -> Board:
    """A grid of ``rows`` x ``columns`` markers of side ``size`` from id ``start_id``, row by row.

    Centres ``size * (1 + spacing)`` apart (``spacing``: the gap over the side), marker axes along
    the board's; ``staggered``: every other cell, starting at column ``row % 2``, rows going down
    (-y) (TagSLAM's ``staggered_board``), else every cell, rows going up (+y) (its ``board``).
    ``T_board_body``: the board description's own pose (TagSLAM's ``pose`` of a staggered board):
    markers at ``T_board_body^-1 * centre``.
    """
    if rows < 1 or columns < 1 or not size > 0 or not spacing >= 0:
        raise GeometryError(f"board {name!r}: expected rows, columns >= 1, size > 0 and spacing >= 0, got "
                            f"{rows}, {columns}, {size}, {spacing}")
    pitch = size * (1.0 + spacing)
    T_pre = geo.inverse(T_board_body) if T_board_body is not None else np.eye(4)
    layout: Dict[int, np.ndarray] = {}
    mid = int(start_id)
    for row in range(rows):
        cols = range(row % 2, columns, 2) if staggered else range(columns)
        for col in cols:
            T = np.eye(4)
            T[:3, 3] = (col * pitch, (-row if staggered else row) * pitch, 0.0)
            layout[mid] = T_pre @ T
            mid += 1
    return Board(name, layout)


def fit_board_pose(board: Board, T_W_markers: Mapping[int, np.ndarray], weights: Optional[Mapping[int, float]] = None,
                   position_tol: float = 0.02, angle_tol: float = np.radians(5.0)) -> Tuple[np.ndarray, List[int]]:
    """``T_W_board`` from the poses of the board's markers in ``T_W_markers``, robustly.

    With three markers or more whose layout centres are not on a line, the board's pose is the
    rigid fit of the layout's centres to the markers' centres, markers farther than
    ``position_tol`` from the fit dropped and the fit redone: the centres do not depend on the
    single-marker orientations, whose IPPE ambiguity at grazing angles mirrors every marker of a
    board the same way (a vote over the markers' poses would side with the mirror). Otherwise each
    marker proposes ``T_W_marker T_board_marker^-1``; the proposal that most others agree with
    (within ``position_tol`` m and ``angle_tol`` rad; ties: the larger weight) wins, and its
    agreeing proposals are averaged (weighted). Returns (pose, the markers that agreed).
    """
    ids = [m for m in board.ids if m in T_W_markers]
    if not ids:
        raise GeometryError(f"board {board.name!r}: none of its markers is placed")
    w = {m: float(weights.get(m, 1.0)) if weights is not None else 1.0 for m in ids}
    if len(ids) >= 3:
        T = _centre_fit(board, ids, T_W_markers, w, position_tol)
        if T is not None:
            return T
    props = {m: T_W_markers[m] @ geo.inverse(board.layout[m]) for m in ids}
    best: Tuple[float, float] = (-1.0, -1.0)
    best_in: List[int] = []
    for m in ids:
        inl = []
        for n in ids:
            dp, da = geo.pose_distance(props[m], props[n])
            if dp <= position_tol and da <= angle_tol:
                inl.append(n)
        score = (float(sum(w[n] for n in inl)), w[m])
        if score > best:
            best, best_in = score, inl
    T = geo.average_transforms([props[n] for n in best_in], [w[n] for n in best_in])
    return T, best_in


def _spans_plane(P: np.ndarray, tol: float = 1e-6) -> bool:
    c = P - P.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    return len(sv) >= 2 and sv[1] > tol * max(sv[0], 1e-12) and sv[1] > 1e-4


def _centre_fit(board: Board, ids: List[int], T_W_markers: Mapping[int, np.ndarray], w: Mapping[int, float],
                tol: float) -> Optional[Tuple[np.ndarray, List[int]]]:
    """(pose, inliers) of :func:`fit_board_pose`'s centre fit; None when the centres cannot fix it."""
    P = {m: board.layout[m][:3, 3] for m in ids}
    Q = {m: np.asarray(T_W_markers[m])[:3, 3] for m in ids}
    keep = list(ids)
    for _ in range(len(ids)):
        if len(keep) < 3 or not _spans_plane(np.array([P[m] for m in keep])):
            return None
        T = geo.rigid_fit([P[m] for m in keep], [Q[m] for m in keep], [w[m] for m in keep])
        d = {m: float(np.linalg.norm(T[:3, :3] @ P[m] + T[:3, 3] - Q[m])) for m in ids}
        worst = max(keep, key=lambda m: d[m])
        if d[worst] <= tol:
            return T, [m for m in ids if d[m] <= tol]
        keep.remove(worst)
    return None


def solve_board_view(board: Board, views: Sequence[Tuple[int, np.ndarray, float, Sequence[np.ndarray]]],
                     focal: np.ndarray) -> Tuple[np.ndarray, float, Dict[int, float]]:
    """The pose of ``board`` in one camera from several of its markers seen at once.

    ``views``: (marker id, its corners (4, 2) undistorted normalised, its side, its single-marker
    candidate poses ``T_cam_marker``). Every candidate of every marker proposes the board's pose
    (``T_cam_marker T_board_marker^-1``); the proposal that reprojects all the corners best is
    refined (Levenberg-Marquardt over all of them): the other markers of the board resolve each
    one's IPPE ambiguity. Returns (``T_cam_board``, RMS over all corners in undistorted px, RMS per
    marker).
    """
    import cv2

    obj = np.concatenate([geo.transform_points(board.layout[m], marker_corners(size)) for m, _, size, _ in views])
    xy = np.concatenate([np.asarray(v[1], dtype=float).reshape(4, 2) for v in views])
    best, best_rms = None, float("inf")
    for m, _, _, cands in views:
        for T in cands:
            T_b = np.asarray(T) @ geo.inverse(board.layout[m])
            r = _undistorted_rms(T_b, obj, xy, focal)
            if r < best_rms:
                best, best_rms = T_b, r
    if best is None:
        raise GeometryError(f"board {board.name!r}: no candidate pose")
    rvec, tvec = geo.rvec_tvec_from_transform(best)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-12)
    rvec, tvec = cv2.solvePnPRefineLM(obj.astype(np.float64), xy.astype(np.float64), np.eye(3), np.zeros(5),
                                      rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy(), criteria=crit)
    T_ref = geo.transform_from_rvec_tvec(rvec.ravel(), tvec.ravel())
    rms = _undistorted_rms(T_ref, obj, xy, focal)
    if not rms <= best_rms:
        T_ref, rms = best, best_rms
    per = {m: _undistorted_rms(T_ref, obj[4 * k:4 * k + 4], xy[4 * k:4 * k + 4], focal)
           for k, (m, _, _, _) in enumerate(views)}
    return T_ref, rms, per


def _undistorted_rms(T: np.ndarray, obj: np.ndarray, xy: np.ndarray, focal) -> float:
    p = obj @ T[:3, :3].T + T[:3, 3]
    if np.any(p[:, 2] <= 1e-9):
        return float("inf")
    d = (p[:, :2] / p[:, 2:3] - xy) * np.asarray(focal, dtype=float)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


@dataclass
class Collapsed:
    """A bundle adjustment problem with every board one unknown (:func:`collapse`).

    Attributes:
        unit: (M,) index of each original marker's unknown in the collapsed problem.
        T_unit_marker: (M, 4, 4) the marker's pose in its unknown's frame (identity for a marker
            on no board, its layout for a board's).
        n_units: number of unknowns.
    """

    unit: np.ndarray
    T_unit_marker: np.ndarray
    n_units: int


def collapse(mids: Sequence[int], T_W_markers: np.ndarray, sizes: np.ndarray, obs_marker: np.ndarray,
             boards: BoardSet) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Collapsed]:
    """The unknowns of a problem over markers ``mids`` (poses ``T_W_markers``, sides ``sizes``)
    with the markers of each board merged into one.

    Returns (``T_W_units`` (U, 4, 4), ``sizes`` (U,) (a board: its first marker's side; the corners
    come from ``obs_object``), ``obs_object`` (N, 4, 3): each observation's corners in its unknown's
    frame, :class:`Collapsed`). A board's starting pose is :func:`fit_board_pose` of its markers'.
    """
    mids = [int(m) for m in mids]
    unit = np.full(len(mids), -1, dtype=int)
    T_um = np.tile(np.eye(4), (len(mids), 1, 1))
    T_units: List[np.ndarray] = []
    u_sizes: List[float] = []
    board_unit: Dict[int, int] = {}
    by_board: Dict[int, List[int]] = {}
    for k, m in enumerate(mids):
        b = boards.board_of(m)
        if b is None:
            unit[k] = len(T_units)
            T_units.append(np.asarray(T_W_markers[k], dtype=float))
            u_sizes.append(float(sizes[k]))
        else:
            by_board.setdefault(b, []).append(k)
    for b, ks in by_board.items():
        board = boards.boards[b]
        T_b, _ = fit_board_pose(board, {mids[k]: T_W_markers[k] for k in ks})
        board_unit[b] = len(T_units)
        T_units.append(T_b)
        u_sizes.append(float(sizes[ks[0]]))
        for k in ks:
            unit[k] = board_unit[b]
            T_um[k] = board.layout[mids[k]]
    obs_marker = np.asarray(obs_marker, dtype=int)
    X = marker_corners(1.0)[None, :, :] * np.asarray(sizes, dtype=float)[obs_marker][:, None, None]
    T = T_um[obs_marker]
    obs_object = X @ np.transpose(T[:, :3, :3], (0, 2, 1)) + T[:, None, :3, 3]
    return np.stack(T_units), np.array(u_sizes), obs_object, Collapsed(unit, T_um, len(T_units))


def expand_poses(T_W_units: np.ndarray, c: Collapsed) -> np.ndarray:
    """(M, 4, 4) marker poses from the collapsed unknowns' poses."""
    return np.asarray(T_W_units)[c.unit] @ c.T_unit_marker


def expand_covariances(cov_units: np.ndarray, T_W_units: np.ndarray, c: Collapsed) -> np.ndarray:
    """(M, 6, 6) marker covariances of (w, t) (rotation in W, translation in W) from the unknowns'.

    A marker at ``T_W_u T_u_m``: ``R_m = exp(w) R_u R_um`` (the same w), ``t_m = exp(w) R_u t_um + t_u``:
    ``dt_m = dt_u - [R_u t_um]x w``.
    """
    out = np.zeros((len(c.unit), 6, 6))
    for k, u in enumerate(c.unit):
        a = np.asarray(T_W_units[u])[:3, :3] @ c.T_unit_marker[k, :3, 3]
        J = np.eye(6)
        J[3:, :3] = -geo.skew(a)
        out[k] = J @ cov_units[u] @ J.T
    return out


def loose_priors(mids: Sequence[int], T_W_markers: np.ndarray, boards: BoardSet
                 ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The board frames and relative priors of the loose boards among markers ``mids`` (poses
    ``T_W_markers``): one frame per loose board with a marker in ``mids``, its start the
    :func:`fit_board_pose` of those markers, numbered after the markers (``len(mids) + j``).

    Returns (frames' poses (F, 4, 4), ``relative_marker`` (Q, 2) (frame index, marker index),
    ``relative_pose`` (Q, 4, 4) the layout, ``relative_position_std`` (Q,) m,
    ``relative_rotation_std`` (Q,) rad, and each frame's board index (F,)).
    """
    by_board: Dict[int, List[int]] = {}
    for k, m in enumerate(mids):
        b = boards.board_of(int(m))
        if b is not None and boards.boards[b].loose:
            by_board.setdefault(b, []).append(k)
    frames: List[np.ndarray] = []
    pairs: List[Tuple[int, int]] = []
    poses: List[np.ndarray] = []
    pos_std: List[float] = []
    rot_std: List[float] = []
    of: List[int] = []
    for b, ks in sorted(by_board.items()):
        board = boards.boards[b]
        T_b, _ = fit_board_pose(board, {int(mids[k]): np.asarray(T_W_markers[k]) for k in ks})
        f = len(mids) + len(frames)
        frames.append(T_b)
        of.append(b)
        for k in ks:
            pairs.append((f, k))
            poses.append(board.layout[int(mids[k])])
            pos_std.append(float(board.tag_position_std))
            rot_std.append(float(np.radians(board.tag_rotation_std_deg)))
    return (np.array(frames).reshape(-1, 4, 4), np.array(pairs, dtype=int).reshape(-1, 2),
            np.array(poses).reshape(-1, 4, 4), np.array(pos_std), np.array(rot_std), np.array(of, dtype=int))


def replace_poses(res, T_W_markers: np.ndarray, marker_cov: Optional[np.ndarray]):
    """A copy of a :class:`bundle_adjustment.BAResult` with the markers' poses and covariances replaced."""
    return dataclasses.replace(res, T_W_markers=T_W_markers, marker_cov=marker_cov)
