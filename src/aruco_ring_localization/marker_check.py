"""Moved-marker detection: each mapped marker checked against the others over time (issue 13).

A marker bumped in the hall otherwise biases every pose that uses it. For every ring frame whose
pose the gate accepted while the robot stood or crept (``max_speed``, ``max_yaw_rate``; frames
taken while it drives are skipped, at no cost), :class:`MarkerCheck` computes, per marker in view:

1. its **leave-one-out residual**: the corners' residuals (normalised image coordinates) against
   the pose estimated from the *other* markers of the frame. The pose from the others is one
   Gauss-Newton step of the frame's least-squares problem without that marker's rows, from the
   measured pose (a rank-6 down-date of the 6x6 normal matrix: cheap, no new solve);
2. the **displacement** of the marker that explains it, linearised: a 3-vector in the map frame,
   as information ``A = sum J^T W J`` and ``b = sum J^T W r`` (``J``: corners w.r.t. the marker's
   position; ``W``: per (camera, marker) block of 4 corners, the inverse of ``s^2 I + j^2 Jr Jr^T``
   with ``s`` = ``pixel_noise / f`` and ``j`` the cameras' per-frame rotation jitter, ``Jr`` the
   corners w.r.t. the camera's rotation), with the uncertainty of the pose from the others
   marginalised (Schur complement), judged against the change from each (marker, camera) pair's
   baseline for the current set of other (camera, marker) pairs (the baselines in :meth:`MarkerCheck.update`).

``A`` and ``b`` are summed over the last ``window`` seconds. The estimated displacement is
``d = A^-1 b`` and the **test statistic**

    T = d^T (A^-1 + sigma_sys^2 I)^-1 d

is chi^2 with 3 degrees of freedom for a marker that did not move, *if* the only errors were the
corner noise (``A^-1``) and a systematic offset of ``systematic_std`` per axis (map and extrinsic
calibration errors, which do not average out over frames). A marker with ``T > threshold`` and
``|d| > min_move`` that has been seen in at least ``min_observations`` frames of the window is
**moved**: it is dropped from the pose (:meth:`strip`), named in the log and reported with ``|d|``.
Only the worst marker is declared per frame, and the evidence of every other marker is discarded
then: it was gathered with the moved one still in their poses.

The computation is vectorised over the frame's blocks: every leave-one-out pose is one batched
6x6 solve, the Schur complements one batched solve, the window sums are kept running.

The default threshold (30, chi^2_3 at about 1e-6) with ``systematic_std`` 5 mm flags a marker whose
window displacement is above about 5.5 sigma_sys; ``min_move`` (2 cm) keeps a well-seen marker
(tiny ``A^-1``) from being flagged for a sub-centimetre map error. The false alarm rate on a long
static and driving run of the simulated lab is measured in the unit tests and the benchmark.

:meth:`MarkerCheck.remap` re-estimates a marker's 6-DOF pose from its recent observations
(``remap_window`` s) with the robot poses from the other markers fixed (the other markers stay
fixed), replaces it in the map in memory and re-admits it. :func:`estimate_marker_pose` is the
same least squares for ``aruco_ring build-map --update``.

No ROS here; the pipeline calls :meth:`strip` before the estimator and :meth:`update` after the gate.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Deque, Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .camera import CameraModel
from .config import param
from .detections import CameraFrame, RingFrame
from .errors import ConfigError, MeasurementError
from .marker_map import MarkerEntry, MarkerMap
from .markers import marker_corners
from .odometry import displacement_to_transform
from .ring import CameraRing

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MarkerCheckParams:
    """Moved-marker detection: per-marker residuals against the pose from the other markers."""

    enabled: bool = param(True, "check every marker in view against the others; a moved one is dropped from "
                                "the pose and reported (docs/localization.md); false: every mapped marker is "
                                "used as mapped, and ~remap_marker refuses")
    window: float = param(1.0, "the residuals of the last this many seconds (stamps) are accumulated per "
                               "marker", unit="s")
    min_observations: int = param(4, "a marker is judged on the window only when seen in at least this many "
                                     "frames of it")
    min_other_markers: int = param(2, "a frame checks a marker only when at least this many other mapped "
                                      "markers are in view (the pose from the others)")
    pixel_noise: float = param(0.5, "1-sigma corner noise of the statistic's noise part", unit="px")
    baseline_time: float = param(20.0, "each (marker, camera) pair's own residual offset (extrinsic calibration, "
                                       "map error) is learnt from its residuals older than the window, averaged "
                                       "over this long; the check judges the change from it", unit="s")
    baseline_distance: float = param(0.1, "a pair's baseline holds within this distance of the camera positions "
                                          "it was learnt at (a viewpoint farther away starts it over: the check "
                                          "judges a marker while the robot stands or creeps)", unit="m")
    systematic_std: float = param(0.005, "per-axis std of a marker's apparent offset change that does not "
                                         "average out (the pose from the others seen from elsewhere): the "
                                         "statistic's floor", unit="m")
    threshold: float = param(30.0, "test statistic T = d^T (A^-1 + systematic_std^2 I)^-1 d (chi^2, 3 dof, "
                                   "for a marker that stayed) above which a marker moved: 30 is chi^2_3 at "
                                   "about 1e-6")
    instant_threshold: float = param(60.0, "the same statistic on the latest frame alone above which a marker "
                                           "moved at once (a sudden bump is dropped before its frame reaches the "
                                           "filter)")
    max_speed: float = param(0.05, "a frame is checked only while the robot is this slow (the larger of the filter's "
                                   "speed and the motion inputs'): while it drives, the cameras' stamps and the "
                                   "viewpoint change faster than a baseline holds (false moves on the harsh lab)",
                             unit="m/s")
    max_yaw_rate: float = param(0.02, "and turns this slowly (the same sources)", unit="rad/s")
    min_move: float = param(0.02, "and its estimated displacement |d| must exceed this", unit="m")
    rate: float = param(5.0, "such frames are checked at most this often (stamps; one within 0.9 / rate of the last "
                             "checked is skipped at no cost): the check's CPU per ring frame scales with rate / the "
                             "ring's frame rate; at least min_observations / window (a marker is judged on that many); 0: every "
                             "frame",
                        unit="Hz")
    remap_window: float = param(30.0, "~remap_marker uses a marker's observations of the last this many "
                                      "seconds", unit="s")
    remap_min_observations: int = param(10, "~remap_marker refuses with fewer observations than this")
    save_on_remap: bool = param(False, "~remap_marker also writes the map file (atomically, keeping `backups` "
                                       "generations); false: only ~save_map writes it")
    backups: int = param(3, "previous versions of the map file kept as .bak, .bak.2, ... when the localizer "
                            "writes it (as the mapper's map/backups)")

    def __post_init__(self) -> None:
        for name in ("window", "pixel_noise", "baseline_time", "baseline_distance", "systematic_std", "threshold",
                     "instant_threshold", "remap_window", "max_speed", "max_yaw_rate"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"must be > 0, got {getattr(self, name)!r}", key=f"marker_check.{name}")
        if not self.min_move >= 0:
            raise ConfigError(f"must be >= 0, got {self.min_move!r}", key="marker_check.min_move")
        if not float(self.rate) >= 0:
            raise ConfigError(f"must be >= 0, got {self.rate!r}", key="marker_check.rate")
        for name in ("min_observations", "min_other_markers", "remap_min_observations", "backups"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"must be >= 1, got {getattr(self, name)!r}", key=f"marker_check.{name}")


@dataclass
class MarkerObservationRecord:
    """One marker seen by one camera, with the robot pose from the other markers (for re-mapping)."""

    stamp: float
    camera: str
    corners: np.ndarray          # (4, 2) raw px
    model: CameraModel
    T_map_cam: np.ndarray        # camera pose from the other markers


@dataclass
class MovedMarker:
    """A marker declared moved."""

    marker_id: int
    since: float                 # stamp of the frame that declared it
    displacement: np.ndarray     # (3,) map frame, m (the latest window estimate)
    statistic: float

    @property
    def distance(self) -> float:
        return float(np.linalg.norm(self.displacement))


class _Evidence:
    """A marker's displacement information over the window: the frames' (stamp, [A | b]) and their
    running sum (kept exactly zero once the window is empty, so no rounding accumulates). A (3x3)
    and b (3) side by side in one (3, 4) array: one array operation per frame and sum, not two."""

    __slots__ = ("items", "Ab")

    def __init__(self) -> None:
        self.items: Deque[Tuple[float, np.ndarray]] = deque()
        self.Ab = np.zeros((3, 4))

    def push(self, stamp: float, Ab: np.ndarray) -> None:
        """One frame's ``[A | b]`` (3, 4) in; the old frames stay until :meth:`prune` (the caller's next step)."""
        self.items.append((stamp, Ab))
        self.Ab = self.Ab + Ab

    def prune(self, oldest: float) -> None:
        """Forget the frames stamped before ``oldest``."""
        items = self.items
        while items and items[0][0] < oldest:
            self.Ab = self.Ab - items.popleft()[1]
        if not items:
            self.clear()

    def clear(self) -> None:
        self.items.clear()
        self.Ab = np.zeros((3, 4))


def _statistics(A: np.ndarray, b: np.ndarray, sys_std: float) -> Tuple[np.ndarray, np.ndarray]:
    """Batched: displacement ``d = A^+ b`` (K, 3) and ``T = d^T (A^+ + sys_std^2 I)^-1 d`` (K,)
    for symmetric positive semi-definite information matrices ``A`` (K, 3, 3) and vectors ``b`` (K, 3).

    ``A^+`` is ``np.linalg.pinv``'s (eigenvalues within 1e-15 of the largest count as zero). With
    ``A_r = A + 1e-12 I`` (the ridge), ``A^+ + s^2 I = A_r^-1 (I + s^2 A_r)``, so
    ``T = d^T (I + s^2 A_r)^-1 b``: both inverses by the adjugate, in one batch (:func:`_inv3`),
    when every ``A_r`` is positive definite with a condition number below 1e5 (bounded by its
    invariants: no eigenvalue is cut then, and the adjugate's rounding stays ~1e-11 relative); else
    from one batched eigh (``A`` is symmetric: its singular values are its eigenvalues' magnitudes):
    with ``A_r = V diag(lam) V^T`` and ``k = 1 / lam`` (0 where cut), ``A^+ + s^2 I = V diag(k + s^2) V^T``,
    so ``T = sum_i (V^T b)_i^2 k_i^2 / (k_i + s^2)``."""
    Ar = A + _EYE3
    s2 = sys_std ** 2
    # trace, sum of the principal 2x2 minors and determinant: all > 0 iff A_r is positive definite;
    # then lam_max <= trace and lam_min >= det / minors, so cond(A_r) <= trace * minors / det.
    Af = Ar.reshape(-1, 9)
    cof = _cofactors(Af)
    trace = Af[:, 0] + Af[:, 4] + Af[:, 8]
    minors = cof[:, 0] + cof[:, 4] + cof[:, 8]
    det = np.einsum("ki,ki->k", Af[:, :3], cof[:, :3])
    if ((det > 0) & (trace > 0) & (minors > 0) & (trace * minors < 1e5 * det)).all():
        k = len(A)
        both = _inv3(np.concatenate([Ar, _EYE3_ONE + s2 * Ar]))    # A_r^-1, (I + s^2 A_r)^-1
        y = np.matmul(both, np.concatenate([b, b])[:, :, None])[:, :, 0]
        d = y[:k]
        return d, np.einsum("ki,ki->k", d, y[k:])
    lam, V = np.linalg.eigh(Ar)
    mag = np.abs(lam)
    keep = mag > 1e-15 * mag.max(axis=1, keepdims=True)
    k = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    beta = np.einsum("kji,kj->ki", V, b)            # V^T b
    kb = k * beta
    d = np.einsum("kij,kj->ki", V, kb)              # V diag(k) V^T b
    return d, np.sum(kb * kb / (k + s2), axis=1)


#: per entry (i, j) of a 3x3 matrix (row-major), the flat indices of M[i+1, j+1], M[i+2, j+2],
#: M[i+1, j+2], M[i+2, j+1] (indices mod 3): its cofactor is the first product minus the second.
_COF = np.array([[4, 5, 3, 7, 8, 6, 1, 2, 0],
                 [8, 6, 7, 2, 0, 1, 5, 3, 4],
                 [5, 3, 4, 8, 6, 7, 2, 0, 1],
                 [7, 8, 6, 1, 2, 0, 4, 5, 3]])


def _cofactors(Mf: np.ndarray) -> np.ndarray:
    """Batched cofactors (K, 9) of 3x3 matrices given flat (K, 9), in four array operations."""
    G = Mf[:, _COF]
    return G[:, 0] * G[:, 1] - G[:, 2] * G[:, 3]


def _inv3(M: np.ndarray) -> np.ndarray:
    """Batched inverse of (K, 3, 3) non-singular matrices by the adjugate (no LAPACK call per matrix)."""
    Mf = M.reshape(-1, 9)
    cof = _cofactors(Mf)
    det = np.einsum("ki,ki->k", Mf[:, :3], cof[:, :3])
    return cof.reshape(-1, 3, 3).transpose(0, 2, 1) / det[:, None, None]


#: the ridges of the 6x6 pose solves and of the 3x3 displacement information
_EYE6 = 1e-12 * np.eye(6)
_EYE3 = 1e-12 * np.eye(3)
_EYE3_ONE = np.eye(3)


def _far(a: Sequence[float], b: Sequence[float], distance2: float) -> bool:
    """|a - b|^2 > distance2 for 3-vectors as lists (np.linalg.norm's set-up costs more than the
    arithmetic: twice per (marker, camera) pair and frame)."""
    x, y, z = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return x * x + y * y + z * z > distance2


@dataclass
class _Baseline:
    """A (marker, camera, basis) pair's offset. Python floats, not arrays: the exponential average of
    8 and 3 numbers costs less than numpy's set-up of its 6 operations (the same IEEE arithmetic,
    element by element: the same numbers)."""

    value: Optional[List[float]] = None      # 8 residuals of the 4 corners, normalised coordinates
    position: Optional[List[float]] = None   # 3: camera position (map) it was learnt at
    count: int = 0
    stamp: Optional[float] = None
    pending: Deque[Tuple[float, List[float], List[float]]] = field(default_factory=deque)


@dataclass
class _View:
    camera: str
    index: int                   # the camera's index in the ring (bit of a basis mask)
    model: CameraModel
    T_cam_base: np.ndarray       # moved by the robot's motion to the camera's stamp (free-running)
    ids: List[int]
    px: Sequence[np.ndarray]     # per marker its (4, 2) raw corners (a list, or a (k, 4, 2) array)
    xy: np.ndarray               # (4k, 2) normalised, undistorted observed corners
    X: np.ndarray                # (4k, 3) map corners


#: where :func:`_rows` writes the skew matrices -[P_base]x (columns 0-2 of its G) and [P_cam]x
#: (columns 10-12) in G's flat (n, 39) rows: (flat index, index in [P_base, P_cam], sign)
_SKEW = np.array([(1, 2, 1), (2, 1, -1), (13, 2, -1), (15, 0, 1), (26, 1, 1), (27, 0, -1),
                  (11, 5, -1), (12, 4, 1), (23, 5, 1), (25, 3, -1), (36, 4, -1), (37, 3, 1)])
_SKEW_AT, _SKEW_OF, _SKEW_SIGN = _SKEW[:, 0], _SKEW[:, 1], _SKEW[:, 2].astype(np.float64)


def _rows(views: Sequence[_View], T_cam_bases: np.ndarray, T_cam_maps: np.ndarray, T_base_map: np.ndarray,
          pixel_noise: float):
    """Every camera's rows in one pass, per (camera, marker) block of 4 corners (8 rows), as one
    array J (B, 8, 13) with the columns: J_pose (0-5) w.r.t. a base-frame perturbation (w, v) of
    ``T_base_map`` (geo.se3_perturb's order), J_marker (6-8) w.r.t. the marker's position in the
    map, the residual r (9) in normalised coordinates, J_rot (10-12) w.r.t. the camera's rotation
    (up to its sign), and the weight 1/s^2 (B,) of the block's camera. ``T_cam_bases``,
    ``T_cam_maps``: the views' (V, 4, 4) stacked (:meth:`MarkerCheck._views`).

    Each Jacobian is D G, with D = d xy / d P_cam = [[1/z, 0, -x/z], [0, 1/z, -y/z]] and G the
    derivatives of the camera-frame point: R_cam_base [-P_base]x for the rotation (a row e^T [-q]x
    is (q x e)^T), R_cam_base for the translation, R_cam_map for the marker, [P_cam]x for the camera
    rotation: one batched product for them all (few array operations: their set-up dominates)."""
    counts = [len(v.X) for v in views]
    X = np.concatenate([v.X for v in views])
    n = len(X)
    # Per corner, its camera's matrices: one gather from the stacks (np.repeat of each stack cost 3x).
    corner_view = np.repeat(np.arange(len(views)), counts)
    G = np.zeros((n, 3, 13))
    G[:, :, 3:9] = np.concatenate([T_cam_bases[:, :3, :3], T_cam_maps[:, :3, :3]], axis=2)[corner_view]
    P = np.matmul(G[:, :, 6:9], X[:, :, None])[:, :, 0] + T_cam_maps[corner_view, :3, 3]
    pred = P[:, :2] / P[:, 2:3]
    Pb = X @ T_base_map[:3, :3].T + T_base_map[:3, 3]
    G.reshape(n, 39)[:, _SKEW_AT] = np.concatenate([Pb, P], axis=1)[:, _SKEW_OF] * _SKEW_SIGN
    G[:, :, :3] = G[:, :, 3:6] @ G[:, :, :3]
    # D G = (G's rows x, y minus the prediction times its row z) / z
    J = (G[:, :2] - pred[:, :, None] * G[:, 2:3]) * (1.0 / P[:, 2])[:, None, None]
    J[:, :, 9] = np.concatenate([v.xy for v in views]) - pred
    # (math.sqrt: np.sqrt's number, correctly rounded, without a ufunc call per camera)
    w = np.array([math.sqrt(v.model.fx * v.model.fy) ** 2 / pixel_noise ** 2 for v in views])[corner_view[::4]]
    return J.reshape(n // 4, 8, 13), w


class _Layout:
    """Which (camera, marker) block is which in one check, and what follows from it alone (the
    views' cameras and marker ids and the dropped markers; no measurement): per block its view, its
    index in the view and its marker's row; the markers in view sorted; which are used in the pose,
    which may be judged (enough other used markers); the marker <- block summing matrix; per marker
    the hash of its set of others (the (camera, marker) pairs of the other used markers: the key of
    its baselines). :meth:`MarkerCheck._layout` keeps the last few."""

    __slots__ = ("blk_view", "blk_k", "blk_m_l", "blk_m", "mids", "M", "used_l", "used", "S", "eligible",
                 "any_eligible", "masks")

    def __init__(self, views: Sequence[_View], drop: set, min_other_markers: int):
        blk_view, blk_k, blk_mid, pairs = [], [], [], []
        own: Dict[int, set] = {}
        for vi, v in enumerate(views):
            cam = v.index
            for k, i in enumerate(v.ids):
                blk_view.append(vi)
                blk_k.append(k)
                blk_mid.append(i)
                pr = (cam, i)
                pairs.append(pr)
                mine = own.get(i)
                if mine is None:
                    own[i] = {pr}
                else:
                    mine.add(pr)
        B = len(blk_mid)
        # The markers in view, sorted, and each block's (np.unique's, without its set-up).
        mids = sorted(own)
        order = {m: j for j, m in enumerate(mids)}
        self.blk_view, self.blk_k = blk_view, blk_k
        self.blk_m_l = [order[i] for i in blk_mid]
        self.blk_m = np.array(self.blk_m_l, dtype=np.intp)
        self.mids, self.M = mids, len(mids)
        self.used_l = [m not in drop for m in mids]
        self.used = np.array(self.used_l, dtype=bool)
        # Marker <- block sums (M rows), and a last row: the sums over the blocks of used markers.
        self.S = np.zeros((self.M + 1, B))
        self.S[self.blk_m, np.arange(B)] = 1.0
        self.S[self.M] = self.used[self.blk_m]
        n_used = sum(self.used_l)
        self.eligible = tuple(n_used - u >= min_other_markers for u in self.used_l)
        self.any_eligible = any(self.eligible)
        everyone = frozenset(pr for pr, mid in zip(pairs, blk_mid) if mid not in drop)
        self.masks = [hash(everyone - own[mid]) for mid in mids]


#: how many block layouts a MarkerCheck keeps (a standing robot repeats one or a few)
_LAYOUTS_KEPT = 16


class MarkerCheck:
    """Per-marker consistency check over time (module docstring).

    Args:
        marker_map: the map in use (shared with the estimator; :meth:`remap` updates it).
        params: :class:`MarkerCheckParams`.
        warn: a throttled warning sink ``warn(key, message, now)`` (the pipeline's).
        extrinsic_jitter: each camera's per-frame rotation jitter (ring vibration), rad per axis:
            it moves all corners of a camera together, so a block's residuals are correlated
            (``s^2 I + jitter^2 Jr Jr^T``, ``Jr``: the corners w.r.t. the camera's rotation). Without
            it two cameras that see a marker "triangulate" a depth change out of their jitter.
    """

    def __init__(self, marker_map: MarkerMap, params: Optional[MarkerCheckParams] = None, warn=None,
                 extrinsic_jitter: float = 0.0):
        self.marker_map = marker_map
        #: per-frame rotation jitter of each camera, rad per axis (the estimator's extrinsic_jitter_deg).
        self.extrinsic_jitter = float(extrinsic_jitter)
        self.params = params or MarkerCheckParams()
        self._warn = warn
        self._evidence: Dict[int, _Evidence] = {}
        # id -> (stamp, camera, px, model, T_map_base, delta, T_cam_base): what a re-map needs,
        # turned into MarkerObservationRecord only when asked (:meth:`observations`).
        self._records: Dict[int, Deque[tuple]] = {}
        self._baselines: Dict[Tuple[int, str, int], _Baseline] = {}
        #: id -> the marker declared moved (dropped from the pose until re-mapped or re-admitted).
        self.moved: Dict[int, MovedMarker] = {}
        #: ids forced out of the pose from outside (``build-map --update``: the markers being re-mapped).
        self.excluded: set = set()
        self.frames_checked = 0
        #: frames not checked because the robot drove or turned (``max_speed``, ``max_yaw_rate``).
        self.frames_moving = 0
        #: frames not checked because one was checked less than 0.9 / ``rate`` s before (``rate``).
        self.frames_skipped = 0
        self._last_checked: Optional[float] = None
        self.declarations = 0
        #: id -> (latest d, T, frames) of every marker judged, for diagnostics and tests.
        self.latest: Dict[int, Tuple[np.ndarray, float, int]] = {}
        #: (ring, {camera: (index, T_base_cam, T_cam_base)}) of the last ring checked (:meth:`_views`).
        self._ring_cameras: Optional[Tuple[CameraRing, Dict[str, Tuple[int, np.ndarray, np.ndarray]]]] = None
        #: (the views' (camera index, ids), the dropped ids) -> its :class:`_Layout` (:meth:`_layout`)
        self._layouts: Dict[tuple, _Layout] = {}

    # --- the pose side -------------------------------------------------------------------------

    @property
    def dropped(self) -> set:
        """Ids kept out of the pose (declared moved, or excluded)."""
        return set(self.moved) | self.excluded

    def strip(self, frame: RingFrame) -> RingFrame:
        """``frame`` without the detections of dropped markers (the input of the estimator)."""
        drop = self.dropped
        if not drop:
            return frame
        out = RingFrame(stamp=frame.stamp, missing=list(frame.missing))
        for name, cf in frame.cameras.items():
            obs = [o for o in cf.observations if int(o.marker_id) not in drop]
            out.cameras[name] = CameraFrame(camera=cf.camera, stamp=cf.stamp, observations=obs, model=cf.model)
        return out

    # --- the check -------------------------------------------------------------------------------

    def _views(self, frame: RingFrame, ring: CameraRing, T_base_map: np.ndarray, motion=None,
               known_views: Optional[Dict[str, object]] = None) -> Tuple[List[_View], np.ndarray, np.ndarray]:
        """The frame's views of mapped markers (``T_base_map``: the inverse of the accepted pose) and
        their T_cam_base and T_cam_map stacked (V, 4, 4) (None without views);
        ``known_views``: the estimator's views of this frame (:attr:`RingLocalizer.last_views`,
        name -> CameraView), whose corners are reused where a camera's markers are the same."""
        mm = self.marker_map
        t_ref = float(frame.stamp)
        if self._ring_cameras is None or self._ring_cameras[0] is not ring:
            # Per camera of this ring: (index, T_base_cam, T_cam_base), built once per ring (the
            # pipeline's ring changes only with new extrinsics or intrinsics).
            self._ring_cameras = (ring, {c.name: (k, c.T_base_cam, geo.inverse(c.T_base_cam))
                                         for k, c in enumerate(ring.cameras)})
        cameras = self._ring_cameras[1]
        out = []
        T_cam_bases = []
        for name, cf in frame.cameras.items():
            known = cameras.get(name)
            if known is None:
                continue
            ids = [int(o.marker_id) for o in cf.observations]
            same = None if known_views is None else known_views.get(name)
            if same is None or same.ids != ids:
                # (else the estimator's view of the same ids: every one mapped, RingLocalizer._gather)
                ids = [i for i in ids if i in mm]
            if not ids:
                continue
            index, T_base_cam, T_cam_base = known
            model = cf.model if cf.model is not None else ring[name].model
            moved = None if motion is None or cf.stamp == t_ref else motion(t_ref, float(cf.stamp))
            if moved is not None:
                # A free-running camera saw the map from where the robot was at its own stamp
                # (as the estimator takes it: RingLocalizer._moved_extrinsics).
                T_base_cam = displacement_to_transform(moved[0]) @ T_base_cam
                T_cam_base = geo.inverse(T_base_cam)
            if same is not None and same.ids == ids and same.model is model:
                # The estimator's view of these very detections (its corners, normalised and in the
                # map, are the same numbers): not computed again.
                px = same.px.reshape(-1, 4, 2)
                xy, X = same.xy, same.X
            else:
                px = [np.asarray(o.corners, dtype=np.float64).reshape(4, 2) for o in cf.observations
                      if int(o.marker_id) in mm]
                xy, X = model.normalize(np.concatenate(px)), np.concatenate([mm.corners(i) for i in ids])
            out.append(_View(name, index, model, T_cam_base, ids, px, xy, X))
            T_cam_bases.append(T_cam_base)
        if not out:
            return out, None, None
        # Every view's T_cam_map in one batched product (the same numbers as one product per view).
        stack = np.array(T_cam_bases)
        return out, stack, np.matmul(stack, T_base_map)

    def _layout(self, views: Sequence[_View], drop: set, min_other_markers: int) -> _Layout:
        """The :class:`_Layout` of these views with these markers dropped: built once, then looked up
        (its arrays are only read). The table holds the last :data:`_LAYOUTS_KEPT` and starts over
        beyond (the robot has gone elsewhere)."""
        key = (tuple((v.index, tuple(v.ids)) for v in views), frozenset(drop), min_other_markers)
        lay = self._layouts.get(key)
        if lay is None:
            if len(self._layouts) >= _LAYOUTS_KEPT:
                self._layouts.clear()
            lay = self._layouts[key] = _Layout(views, drop, min_other_markers)
        return lay

    def update(self, frame: RingFrame, T_map_base: np.ndarray, ring: CameraRing, now: float,
               motion=None, speed: Tuple[float, float] = (0.0, 0.0),
               known_views: Optional[Dict[str, object]] = None) -> List[MovedMarker]:
        """Check the markers of ``frame`` (raw, with dropped markers) against the accepted pose
        ``T_map_base`` (measured without the dropped markers); returns the markers declared moved now.
        ``motion``: the pipeline's ``motion(t_ref, t_c) -> (d, cov_d)`` or None (see
        :meth:`RingLocalizer.process`): each free-running camera is taken at its own stamp.
        ``speed``: the robot's (speed m/s, |yaw rate| rad/s); above ``max_speed`` or
        ``max_yaw_rate`` the frame is not checked (``frames_moving``): nothing is computed.

        Vectorised over the frame's (camera, marker) blocks of 4 corners: the leave-one-out poses
        are one batched 6x6 solve, the displacement information one batched Schur complement."""
        p = self.params
        if speed[0] > p.max_speed or speed[1] > p.max_yaw_rate:
            self.frames_moving += 1
            return []
        stamp = float(frame.stamp)
        rate = max(float(p.rate), p.min_observations / p.window) if p.rate > 0 else 0.0
        if rate > 0 and self._last_checked is not None and 0.0 <= stamp - self._last_checked < 0.9 / rate:
            # At most ``rate`` checks per second (0.9: a ring at 2 x rate, its stamps jittering, is
            # checked every other frame, not every third).
            self.frames_skipped += 1
            return []
        self._last_checked = stamp
        T_base_map = geo.inverse(T_map_base)
        views, T_cam_bases, T_cam_maps = self._views(frame, ring, T_base_map, motion, known_views)
        if not views:
            return []
        drop = self.dropped
        # Blocks: one (camera, marker) pair, its 8 rows.
        J, w = _rows(views, T_cam_bases, T_cam_maps, T_base_map, p.pixel_noise)
        B = len(w)
        # Which block is which (pure functions of the views' cameras and ids and of the dropped
        # markers): the same from check to check while the robot stands, so kept (:meth:`_layout`).
        lay = self._layout(views, drop, p.min_other_markers)
        blk_view, blk_k, blk_m_l, blk_m = lay.blk_view, lay.blk_k, lay.blk_m_l, lay.blk_m
        mids_l, M, used_l, used, S = lay.mids, lay.M, lay.used_l, lay.used, lay.S
        # J = [Z Jr], Z = [Jp Jm r]. Per block, Z^T W Z (10x10): [[H_b, cross^T, g_b], [cross, A, .],
        # [., ., .]] (pose, marker, residual) from the Gram matrix J^T J (one product), with W the block's weight: the
        # inverse of s^2 I + jitter^2 Jr Jr^T (8x8; s^2 = 1 / w), by Woodbury on 3x3:
        # W = w (I - Jr K^-1 Jr^T), K = s^2 / jitter^2 I + Jr^T Jr (a batched 8x8 inverse cost twice
        # as much). ``C`` = K^-1 Jr^T Z gives W Z = w (Z - Jr C) where needed (the judged blocks).
        gram = J.transpose(0, 2, 1) @ J                                  # (B, 13, 13)
        if self.extrinsic_jitter > 0:
            JrTZ = gram[:, 10:, :10]
            gram.reshape(B, 169)[:, 140::14] += (1.0 / (w * self.extrinsic_jitter ** 2))[:, None]   # Jr^T Jr -> K
            C = _inv3(gram[:, 10:, 10:]) @ JrTZ
            NZ = (gram[:, :10, :10] - JrTZ.transpose(0, 2, 1) @ C) * w[:, None, None]
        else:
            C = None
            NZ = gram[:, :10, :10] * w[:, None, None]
        sums = (S @ NZ.reshape(B, 100)).reshape(M + 1, 10, 10)
        Hm, gm = sums[:M, :6, :6], sums[:M, :6, 9]
        H_all, g_all = sums[M, :6, :6], sums[M, :6, 9]
        self.frames_checked += 1
        if self.frames_checked % 100 == 0:
            self._forget(stamp)
        eligible_l = lay.eligible
        if not lay.any_eligible:
            return self._judge(stamp, now)
        # The pose from the others: one Gauss-Newton step without the marker's rows.
        H_loo = H_all[None] - Hm * used[:, None, None]
        g_loo = g_all[None] - gm * used[:, None]
        eye6 = _EYE6
        try:
            delta = np.linalg.solve(H_loo + eye6, g_loo[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            delta = np.zeros((M, 6))
            eligible_l = list(eligible_l)   # (the layout's is shared with later checks)
            for m in range(M):
                if not eligible_l[m]:
                    continue
                try:
                    delta[m] = np.linalg.solve(H_loo[m] + eye6, g_loo[m])
                except np.linalg.LinAlgError:
                    eligible_l[m] = False
        res = J[:, :, 9] - np.matmul(J[:, :, :6], delta[blk_m][:, :, None])[:, :, 0]
        # The (camera, marker) pairs that give the pose from the others: each camera's extrinsic
        # error pulls that pose its own way, and each marker seen weighs in, so the offset a
        # (marker, camera) pair shows holds for one set of others. A camera dropping out, or another
        # marker coming into view, changes the set: the pair's residual jumps although nothing
        # moved (on the harsh lab, 6 mrad when cam4 started to see one more marker); it is judged
        # against the baseline of the new set once that is learnt.
        masks = lay.masks   # per marker: its set of others (the layout's)
        # Camera positions in the map, -R^T t, batched (8 small matmuls on strided views cost ~20 us).
        positions = (-np.einsum("kji,kj->ki", T_cam_maps[:, :3, :3], T_cam_maps[:, :3, 3])).tolist()
        judged_blocks, bases = [], []   # the blocks with a baseline, and it (e = res - base there)
        res_rows, delta_rows = res.tolist(), list(delta)
        records, oldest_record = self._records, stamp - p.remap_window
        # Each block's (marker, camera, others) pair: its offset learnt from its residuals older than
        # the window (None: none yet, the block is not judged); its residual queued for it (inline:
        # one Python pass over the blocks with the parameters bound once, issue 16).
        #
        # A residual joins the baseline once it is ``window`` s old (a plain mean at first, then an
        # exponential average over ``baseline_time``), so a move is judged against what the pair
        # showed before it. The offset depends on the viewpoint (a calibration error projects
        # differently from elsewhere): a baseline is valid within ``baseline_distance`` of the camera
        # positions it was learnt at, and starts over beyond. A baseline that no residual refreshed
        # for ``baseline_time`` starts over too (the robot came back after a loop: learnt from another
        # heading, the same place is another view). The baseline of a dropped marker is frozen.
        baselines, oldest = self._baselines, stamp - p.window
        baseline_time, stale = p.baseline_time, p.window + p.baseline_time
        far2 = p.baseline_distance * p.baseline_distance
        for b_, m in enumerate(blk_m_l):
            if not eligible_l[m]:
                continue
            mid = mids_l[m]
            vi = blk_view[b_]
            v = views[vi]
            camera = v.camera
            # The view for re-mapping (:meth:`observations`), the last ``remap_window`` s of it.
            q = records.get(mid)
            if q is None:
                q = records[mid] = deque()
            q.append((stamp, camera, v.px[blk_k[b_]], v.model, T_map_base, delta_rows[m], v.T_cam_base))
            while q[0][0] < oldest_record:
                q.popleft()
            position = positions[vi]
            key = (mid, camera, masks[m])
            bl = baselines.get(key)
            if bl is None:
                bl = baselines[key] = _Baseline()
            pending = bl.pending
            pending.append((stamp, res_rows[b_], position))
            if pending[0][0] < oldest:
                frozen = mid in drop
                while pending and pending[0][0] < oldest:
                    t, rr, pos = pending.popleft()
                    if frozen:
                        continue
                    if bl.value is None or t - bl.stamp > baseline_time or _far(pos, bl.position, far2):
                        bl.value, bl.position, bl.count, bl.stamp = list(rr), list(pos), 1, t
                        continue
                    bl.count += 1
                    alpha = max(1.0 / bl.count, min(1.0, (t - bl.stamp) / baseline_time))
                    bl.value = [a + alpha * (x - a) for a, x in zip(bl.value, rr)]
                    bl.position = [a + alpha * (x - a) for a, x in zip(bl.position, pos)]
                    bl.stamp = t
            base = bl.value
            if base is None or stamp - bl.stamp > stale or _far(position, bl.position, far2):
                continue   # a pair not seen long enough (or from here) to know its own offset yet
            judged_blocks.append(b_)
            bases.append(base)
        if not judged_blocks:
            return self._judge(stamp, now)
        e = res[judged_blocks] - np.array(bases)
        eJ = (e[:, None, :] @ J[judged_blocks])[:, 0]                    # e^T J (k, 13)
        WJe = eJ[:, :9]                                                  # [Jp Jm]^T W e = w (e^T Z - e^T Jr C)
        if C is not None:
            WJe = WJe - (eJ[:, None, 10:] @ C[judged_blocks, :, :9])[:, 0]
        WJe = WJe * w[judged_blocks, None]
        # The pose from the others is uncertain too (few markers, one camera): the residual's
        # covariance is W^-1 + Jp H^-1 Jp^T. Its inverse (Woodbury) W - W Jp H_joint^-1 Jp^T W
        # turns the sums into the displacement's information with the pose marginalised (the
        # Schur complement): a displacement that the pose from a few markers can absorb is weak
        # evidence, so a frame with few cameras or markers does not declare a move.
        Sh = S[:M, judged_blocks]
        # Per marker, the sums over its judged blocks of Z^T W Z (H_b, cross, A) and [Jp Jm]^T W e (proj, b).
        M9 = Sh @ np.concatenate([NZ[judged_blocks].reshape(-1, 100), WJe], axis=1)
        N_m = M9[:, :100].reshape(M, 10, 10)
        A = N_m[:, 6:9, 6:9]
        b = M9[:, 106:]
        cross = N_m[:, 6:9, :6]
        proj = M9[:, 100:106]
        H_joint = H_loo + N_m[:, :6, :6]
        judged = Sh.any(axis=1).nonzero()[0]   # the markers with a judged block
        try:
            K = np.linalg.solve(H_joint[judged] + eye6, cross[judged].transpose(0, 2, 1))   # (k, 6, 3)
        except np.linalg.LinAlgError:
            return self._judge(stamp, now)
        A = A[judged] - cross[judged] @ K
        A = 0.5 * (A + A.transpose(0, 2, 1))
        b = b[judged] - (K.transpose(0, 2, 1) @ proj[judged][:, :, None])[:, :, 0]
        evidence = self._evidence
        for m, Ab in zip(judged.tolist(), np.concatenate([A, b[:, :, None]], axis=2)):
            ev = evidence.get(mids_l[m])
            if ev is None:
                ev = evidence[mids_l[m]] = _Evidence()
            ev.push(stamp, Ab)
        return self._judge(stamp, now)   # (it prunes every marker's evidence to the window)

    def _forget(self, stamp: float) -> None:
        """Drop the baselines that nothing refreshed for ``window + baseline_time`` (stale: they
        would start over) and whose queue is empty by then: the table stays as large as what is in view."""
        horizon = stamp - self.params.window - self.params.baseline_time
        for key in [k for k, bl in self._baselines.items()
                    if (bl.stamp is None or bl.stamp < horizon) and (not bl.pending or bl.pending[-1][0] < horizon)]:
            del self._baselines[key]

    def _judge(self, stamp: float, now: float) -> List[MovedMarker]:
        p = self.params
        oldest = stamp - p.window
        ids, Abs, counts, fresh = [], [], [], []
        for mid, ev in self._evidence.items():
            items = ev.items
            if not items or items[0][0] < oldest:   # (else nothing to forget: no call)
                ev.prune(oldest)
                if not items:
                    continue
            ids.append(mid)
            Abs.append(ev.Ab)
            counts.append(len(ev.items))
            if ev.items[-1][0] == stamp:
                fresh.append(len(ids) - 1)
        if not ids:
            return []
        # The window sums and the latest frame alone (``fresh``) in one batch.
        Ab = np.array(Abs + [self._evidence[ids[j]].items[-1][1] for j in fresh])
        d_both, T_both = _statistics(Ab[:, :, :3], Ab[:, :, 3], p.systematic_std)
        k = len(ids)
        d_all, T_all = d_both[:k], T_both[:k].tolist()
        dist = np.sqrt(np.einsum("ki,ki->k", d_both, d_both)).tolist()
        instant = {j: (d_both[k + i], T_both[k + i], dist[k + i]) for i, j in enumerate(fresh)}
        worst: Optional[Tuple[int, np.ndarray, float]] = None
        for j, mid in enumerate(ids):
            d, T, n = d_all[j], T_all[j], counts[j]
            self.latest[mid] = (d, T, n)
            if mid in self.moved:
                self.moved[mid].displacement = d
                self.moved[mid].statistic = T
                continue
            if mid in self.excluded:
                continue
            if n >= p.min_observations and T > p.threshold and dist[j] > p.min_move and (
                    worst is None or T > worst[2]):
                worst = (mid, d, T)
            if j in instant:
                d1, T1, dist1 = instant[j]
                T1 = float(T1)
                if T1 > p.instant_threshold and dist1 > p.min_move and (
                        worst is None or T1 > worst[2]):
                    worst = (mid, d1, T1)
        if worst is None:
            return []
        mid, d, T = worst
        mm = MovedMarker(mid, stamp, d, T)
        self.moved[mid] = mm
        self.declarations += 1
        for other in list(self._evidence):
            if other not in self.moved:
                self._evidence[other].clear()
        q = self._records.get(mid)
        while q and q[0][0] < stamp:
            q.popleft()   # where it was: re-mapping uses what it shows from the declaration on
        for (m, _, _), bl in self._baselines.items():
            if m != mid:
                bl.pending.clear()   # residuals taken with the moved marker in the pose: never a baseline
        logger.warning("marker check: marker %d moved by %.1f cm (%s m in the map frame; statistic %.0f > "
                       "marker_check/threshold %.0f): dropped from the pose; re-map it with ~remap_marker or "
                       "build-map --update", mid, 100 * mm.distance,
                       np.array2string(d, precision=3, suppress_small=True), T, p.threshold)
        return [mm]

    def warn_moved(self, now: float) -> None:
        """The throttled reminder that markers are out of the pose (once per warn period)."""
        if self._warn is None or not self.moved:
            return
        text = ", ".join(f"{m.marker_id} ({100 * m.distance:.1f} cm)" for m in self.moved.values())
        self._warn("moved markers", f"marker check: moved markers dropped from the pose: {text}; re-map with "
                                    "~remap_marker", now)

    # --- re-mapping -------------------------------------------------------------------------------

    def observations(self, marker_id: int) -> List[MarkerObservationRecord]:
        """The marker's recent views, each with the camera pose from the other markers."""
        out = []
        for stamp, camera, px, model, T_map_base, delta, T_cam_base in self._records.get(int(marker_id), ()):
            # T_base_map' = exp(delta) T_base_map  ->  T_map_cam' = (T_cam_base T_base_map')^-1
            T_base_map = geo.se3_perturb(geo.inverse(T_map_base), delta)
            out.append(MarkerObservationRecord(stamp, camera, px, model, geo.inverse(T_cam_base @ T_base_map)))
        return out

    def remap(self, marker_id: int) -> Tuple[MarkerEntry, float]:
        """Re-estimate ``marker_id`` from its recent observations (others fixed), put it in the map,
        re-admit it. Returns (new entry, how far it moved, m). Raises MeasurementError (too few
        observations, a marker not in the map)."""
        mid = int(marker_id)
        if mid not in self.marker_map:
            raise MeasurementError(f"marker {mid} is not in the map (ids {self.marker_map.ids[:20]}...)")
        recs = self.observations(mid)
        if len(recs) < self.params.remap_min_observations:
            raise MeasurementError(f"marker {mid}: {len(recs)} observations in the last "
                                   f"{self.params.remap_window:.0f} s (marker_check/remap_window), "
                                   f"{self.params.remap_min_observations} needed: drive where a camera sees it")
        old = self.marker_map[mid]
        T_new, rms = estimate_marker_pose(recs, old.size, old.T_map_marker)
        entry = MarkerEntry(mid, T_new, old.size, position_std=old.position_std, rotation_std=old.rotation_std,
                            observations=len(recs) * 4, ambiguous=False, rms_px=rms)
        self.marker_map.add(entry)
        moved = float(np.linalg.norm(T_new[:3, 3] - old.T_map_marker[:3, 3]))
        self.readmit(mid)
        logger.info("marker check: marker %d re-mapped from %d observations (others fixed): moved %.1f cm, "
                    "RMS %.2f px", mid, len(recs), 100 * moved, rms)
        return entry, moved

    def readmit(self, marker_id: int) -> None:
        """Use the marker in the pose again and forget its evidence and observations."""
        mid = int(marker_id)
        self.moved.pop(mid, None)
        self._evidence.pop(mid, None)
        self._records.pop(mid, None)
        self.latest.pop(mid, None)
        for key in [k for k in self._baselines if k[0] == mid]:
            del self._baselines[key]

    def reset(self) -> None:
        """Forget the evidence (the track restarted); declared markers stay dropped."""
        for ev in self._evidence.values():
            ev.clear()
        self._last_checked = None


def estimate_marker_pose(records: Sequence[MarkerObservationRecord], size: float,
                         T_init: np.ndarray) -> Tuple[np.ndarray, float]:
    """The marker pose ``T_map_marker`` from ``records`` (camera poses fixed): per camera, the pose
    that best reprojects its views (:func:`_fit_marker_pose`), then the average over cameras
    weighted by their views. Not one fit over every camera: two cameras of the ring see a marker
    4 m away under a few degrees, so their relative calibration error (0.15 deg) would put its
    depth 15 cm off by triangulation; each camera's own depth (from the marker's size, averaged
    over its views) is good to millimetres. Returns (T, RMS px of every view at T)."""
    if not records:
        raise MeasurementError("no observations")
    cams: Dict[str, List[MarkerObservationRecord]] = {}
    for r in records:
        cams.setdefault(r.camera, []).append(r)
    fits = [(_fit_marker_pose(rs, size, T_init)[0], len(rs)) for rs in cams.values()]
    w = [n for _, n in fits]
    T = np.eye(4)
    T[:3, :3] = geo.average_rotations([F[:3, :3] for F, _ in fits], w)
    T[:3, 3] = np.average([F[:3, 3] for F, _ in fits], axis=0, weights=w)
    obj = marker_corners(size)
    err = [r.model.project(geo.transform_points(geo.inverse(r.T_map_cam) @ T, obj)) - r.corners for r in records]
    return T, float(np.sqrt(np.mean(np.sum(np.concatenate(err) ** 2, axis=1))))


def _fit_marker_pose(records: Sequence[MarkerObservationRecord], size: float,
                     T_init: np.ndarray) -> Tuple[np.ndarray, float]:
    """The marker pose that best reprojects ``records``: robust (soft-L1 at 2 px) least squares over
    its 6 DOF from ``T_init`` and from the views' IPPE poses (the lowest cost wins). (T, RMS px)."""
    from scipy.optimize import least_squares

    from .pnp import solve_marker_ippe

    if not records:
        raise MeasurementError("no observations")
    obj = marker_corners(size)
    T_cm = [geo.inverse(r.T_map_cam) for r in records]
    px = np.stack([r.corners for r in records])

    def local(T0: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``T0`` moved by ``x`` (rotation vector, translation) in the marker's own frame."""
        return T0 @ geo.se3_perturb(np.eye(4), x)

    def residuals(x: np.ndarray, T0: np.ndarray) -> np.ndarray:
        T = local(T0, x)
        Xm = geo.transform_points(T, obj)
        out = []
        for rec, Tc, p in zip(records, T_cm, px):
            out.append(rec.model.project(geo.transform_points(Tc, Xm)) - p)
        return np.concatenate(out).ravel()

    starts = [np.asarray(T_init, dtype=np.float64)]
    try:
        views = []
        for rec in records:
            cand = solve_marker_ippe(rec.corners, size, rec.model)
            views.append(rec.T_map_cam @ cand.poses[0])
        # A bump mostly translates: the mapped orientation at the views' mean position, and each
        # camera's first view as it is (the mean of rotations of ambiguous views can be anything).
        T = starts[0].copy()
        T[:3, 3] = np.median([V[:3, 3] for V in views], axis=0)
        starts.append(T)
        seen = set()
        for rec, V in zip(records, views):
            if rec.camera not in seen:
                seen.add(rec.camera)
                starts.append(V)
    except (MeasurementError, ValueError, np.linalg.LinAlgError):
        pass
    best = None
    for T0 in starts:
        sol = least_squares(residuals, np.zeros(6), args=(T0,), loss="soft_l1", f_scale=2.0, max_nfev=100)
        cost = float(np.mean(sol.fun ** 2))
        if best is None or cost < best[1]:
            best = (local(T0, sol.x), cost)
    T, mse = best
    return T, float(np.sqrt(mse * 2.0))  # per-corner RMS (x and y)


def parse_marker_ids(values: Iterable) -> List[int]:
    """Ids from ``[17, "18", "3,4"]`` (a service's or a CLI's list); raises ValueError naming the bad one."""
    out: List[int] = []
    for v in values:
        for part in str(v).replace(",", " ").split():
            try:
                out.append(int(part))
            except ValueError:
                raise ValueError(f"marker id {part!r} is not an integer") from None
    return out


__all__ = ["MarkerCheck", "MarkerCheckParams", "MovedMarker", "MarkerObservationRecord", "estimate_marker_pose",
           "parse_marker_ids"]
