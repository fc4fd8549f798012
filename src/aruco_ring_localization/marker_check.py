"""Moved-marker detection: each mapped marker checked against the others over time (issue 13).

A marker bumped in the hall otherwise biases every pose that uses it. For every ring frame whose
pose the gate accepted, :class:`MarkerCheck` computes, per marker in view:

1. its **leave-one-out residual**: the corners' residuals (normalised image coordinates) against
   the pose estimated from the *other* markers of the frame. The pose from the others is one
   Gauss-Newton step of the frame's least-squares problem without that marker's rows, from the
   measured pose (a rank-6 down-date of the 6x6 normal matrix: cheap, no new solve);
2. the **displacement** of the marker that explains it, linearised: a 3-vector in the map frame,
   as information ``A = sum J^T J / s^2`` and ``b = sum J^T r / s^2`` (``J``: corners w.r.t. the
   marker's position, ``s``: ``pixel_noise / f``).

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

The default threshold (30, chi^2_3 at about 1e-6) with ``systematic_std`` 1 cm flags a marker whose
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
from .ring import CameraRing

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MarkerCheckParams:
    """Moved-marker detection: per-marker residuals against the pose from the other markers."""

    enabled: bool = param(False, "check every marker in view against the others; a moved one is dropped from "
                                 "the pose and reported (docs/localization.md). Off by default: with 4 of 8 "
                                 "cameras silent it dropped good markers (7 cm error in the faults_cameras rostest)")
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
    min_move: float = param(0.02, "and its estimated displacement |d| must exceed this", unit="m")
    remap_window: float = param(30.0, "~remap_marker uses a marker's observations of the last this many "
                                      "seconds", unit="s")
    remap_min_observations: int = param(10, "~remap_marker refuses with fewer observations than this")
    save_on_remap: bool = param(False, "~remap_marker also writes the map file (atomically, keeping `backups` "
                                       "generations); false: only ~save_map writes it")
    backups: int = param(3, "previous versions of the map file kept as .bak, .bak.2, ... when the localizer "
                            "writes it (as the mapper's map/backups)")

    def __post_init__(self) -> None:
        for name in ("window", "pixel_noise", "baseline_time", "baseline_distance", "systematic_std", "threshold",
                     "instant_threshold", "remap_window"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"must be > 0, got {getattr(self, name)!r}", key=f"marker_check.{name}")
        if not self.min_move >= 0:
            raise ConfigError(f"must be >= 0, got {self.min_move!r}", key="marker_check.min_move")
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


@dataclass
class _Evidence:
    items: Deque[Tuple[float, np.ndarray, np.ndarray]] = field(default_factory=deque)  # (stamp, A, b)

    def add(self, stamp: float, A: np.ndarray, b: np.ndarray, window: float) -> None:
        self.items.append((stamp, A, b))
        while self.items and self.items[0][0] < stamp - window:
            self.items.popleft()

    def estimate(self, sys_std: float, last: bool = False) -> Tuple[np.ndarray, float, int]:
        """(displacement d, statistic T, frames) over the window (``last``: the latest frame alone)."""
        items = list(self.items)[-1:] if last else self.items
        A = sum(a for _, a, _ in items)
        b = sum(v for _, _, v in items)
        cov = np.linalg.pinv(A + 1e-12 * np.eye(3))
        d = cov @ b
        T = float(d @ np.linalg.solve(cov + sys_std ** 2 * np.eye(3), d))
        return d, T, len(self.items)


@dataclass
class _Baseline:
    value: Optional[np.ndarray] = None       # (8,) residual of the 4 corners, normalised coordinates
    position: Optional[np.ndarray] = None    # (3,) camera position (map) it was learnt at
    count: int = 0
    stamp: Optional[float] = None
    pending: Deque[Tuple[float, np.ndarray, np.ndarray]] = field(default_factory=deque)


@dataclass
class _View:
    camera: str
    model: CameraModel
    R_cam_map: np.ndarray
    t_cam_map: np.ndarray
    T_cam_base: np.ndarray
    ids: List[int]
    px: List[np.ndarray]
    xy: np.ndarray               # (4k, 2) normalised, undistorted observed corners
    X: np.ndarray                # (4k, 3) map corners


def _projection_rows(R_cam_map: np.ndarray, t_cam_map: np.ndarray, X: np.ndarray):
    """Predicted normalised corners (n, 2), d xy / d P_cam (n, 2, 3), P_cam (n, 3)."""
    P = X @ R_cam_map.T + t_cam_map
    z = P[:, 2]
    xy = P[:, :2] / z[:, None]
    D = np.zeros((len(X), 2, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0 / z
    D[:, :, 2] = -xy / z[:, None]
    return xy, D, P


class MarkerCheck:
    """Per-marker consistency check over time (module docstring).

    Args:
        marker_map: the map in use (shared with the estimator; :meth:`remap` updates it).
        params: :class:`MarkerCheckParams`.
        warn: a throttled warning sink ``warn(key, message, now)`` (the pipeline's).
    """

    def __init__(self, marker_map: MarkerMap, params: Optional[MarkerCheckParams] = None, warn=None):
        self.marker_map = marker_map
        self.params = params or MarkerCheckParams()
        self._warn = warn
        self._evidence: Dict[int, _Evidence] = {}
        self._records: Dict[int, Deque[MarkerObservationRecord]] = {}
        self._baselines: Dict[Tuple[int, str, frozenset], _Baseline] = {}
        #: id -> the marker declared moved (dropped from the pose until re-mapped or re-admitted).
        self.moved: Dict[int, MovedMarker] = {}
        #: ids forced out of the pose from outside (``build-map --update``: the markers being re-mapped).
        self.excluded: set = set()
        self.frames_checked = 0
        self.declarations = 0
        #: id -> (latest d, T, frames) of every marker judged, for diagnostics and tests.
        self.latest: Dict[int, Tuple[np.ndarray, float, int]] = {}

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

    def _views(self, frame: RingFrame, ring: CameraRing, T_map_base: np.ndarray) -> List[_View]:
        mm = self.marker_map
        T_base_map = geo.inverse(T_map_base)
        out = []
        for name, cf in frame.cameras.items():
            if name not in ring.names:
                continue
            obs = [o for o in cf.observations if int(o.marker_id) in mm]
            if not obs:
                continue
            cam = ring[name]
            model = cf.model if cf.model is not None else cam.model
            T_cam_base = geo.inverse(cam.T_base_cam)
            T_cam_map = T_cam_base @ T_base_map
            px = [np.asarray(o.corners, dtype=np.float64).reshape(4, 2) for o in obs]
            out.append(_View(name, model, T_cam_map[:3, :3], T_cam_map[:3, 3], T_cam_base,
                             [int(o.marker_id) for o in obs], px, model.normalize(np.concatenate(px)),
                             np.concatenate([mm.corners(int(o.marker_id)) for o in obs])))
        return out

    def update(self, frame: RingFrame, T_map_base: np.ndarray, ring: CameraRing, now: float) -> List[MovedMarker]:
        """Check the markers of ``frame`` (raw, with dropped markers) against the accepted pose
        ``T_map_base`` (measured without the dropped markers); returns the markers declared moved now."""
        p = self.params
        views = self._views(frame, ring, T_map_base)
        if not views:
            return []
        stamp = float(frame.stamp)
        drop = self.dropped
        # Rows of the pose problem: per corner, r (2,), J_pose (2, 6) w.r.t. a base-frame perturbation
        # of T_base_map, J_marker (2, 3) w.r.t. the marker's position in the map, weight 1/s^2.
        T_base_map = geo.inverse(T_map_base)
        per_marker: Dict[int, List[Tuple[np.ndarray, np.ndarray, np.ndarray, float]]] = {}
        for v in views:
            pred, D, _ = _projection_rows(v.R_cam_map, v.t_cam_map, v.X)
            r = v.xy - pred
            Pb = v.X @ T_base_map[:3, :3].T + T_base_map[:3, 3]
            R_cb = v.T_cam_base[:3, :3]
            dPb = np.zeros((len(Pb), 3, 6))
            dPb[:, :, :3] = -np.array([geo.skew(q) for q in Pb])   # (w, v): geo.se3_perturb's order
            dPb[:, :, 3:] = np.eye(3)
            J_pose = np.einsum("nij,jk,nkl->nil", D, R_cb, dPb)
            J_mark = np.einsum("nij,jk->nik", D, v.R_cam_map)
            s = p.pixel_noise / float(np.sqrt(v.model.fx * v.model.fy))
            w = 1.0 / s ** 2
            for k, mid in enumerate(v.ids):
                sl = slice(4 * k, 4 * k + 4)
                per_marker.setdefault(mid, []).append((r[sl], J_pose[sl], J_mark[sl], w, v, k))
        used = [m for m in per_marker if m not in drop]
        H_all = np.zeros((6, 6))
        g_all = np.zeros(6)
        Hm: Dict[int, np.ndarray] = {}
        gm: Dict[int, np.ndarray] = {}
        for mid in used:
            H = np.zeros((6, 6))
            g = np.zeros(6)
            for r, Jp, _, w, _, _ in per_marker[mid]:
                Jf = Jp.reshape(-1, 6)
                H += w * Jf.T @ Jf
                g += w * Jf.T @ r.reshape(-1)
            Hm[mid], gm[mid] = H, g
            H_all += H
            g_all += g
        self.frames_checked += 1
        for mid, rows in per_marker.items():
            others = [m for m in used if m != mid]
            if len(others) < p.min_other_markers:
                continue
            if mid in drop:
                H, g = H_all, g_all
            else:
                H, g = H_all - Hm[mid], g_all - gm[mid]
            try:
                delta = np.linalg.solve(H + 1e-12 * np.eye(6), g)   # the pose from the others, one GN step
            except np.linalg.LinAlgError:
                continue
            # The cameras that give the pose from the others: each camera's extrinsic error moves
            # that pose its own way, so the offset a (marker, camera) pair shows holds for one set.
            # A camera dropping out changes the set: the pair's residual jumps although nothing
            # moved; it is judged against the baseline of the new set once that is learnt.
            basis = frozenset(v.camera for m in others for _, _, _, _, v, _ in per_marker[m])
            A = np.zeros((3, 3))
            b = np.zeros(3)
            H_joint = H.copy()          # the pose's information from the others and these rows
            cross = np.zeros((3, 6))    # sum w Jm^T Jp
            proj = np.zeros(6)          # sum w Jp^T e
            n = 0
            for r, Jp, Jm, w, v, k in rows:
                Jpf = Jp.reshape(-1, 6)
                res = r.reshape(-1) - Jpf @ delta
                self._record(mid, stamp, v, k, T_map_base, delta)
                base = self._baseline_of(mid, v.camera, basis, stamp, res, -v.R_cam_map.T @ v.t_cam_map)
                if base is None:
                    continue   # a pair not seen long enough to know its own offset yet
                Jmf = Jm.reshape(-1, 3)
                e = res - base
                A += w * Jmf.T @ Jmf
                b += w * Jmf.T @ e
                cross += w * Jmf.T @ Jpf
                proj += w * Jpf.T @ e
                H_joint += w * Jpf.T @ Jpf
                n += 1
            if n:
                # The pose from the others is uncertain too (few markers, one camera): the residual's
                # covariance is W^-1 + Jp H^-1 Jp^T. Its inverse (Woodbury) W - W Jp H_joint^-1 Jp^T W
                # turns the sums into the displacement's information with the pose marginalised (the
                # Schur complement): a displacement that the pose from a few markers can absorb is
                # weak evidence, so a frame with few cameras or markers does not declare a move.
                try:
                    K = np.linalg.solve(H_joint + 1e-12 * np.eye(6), cross.T)   # (6, 3)
                except np.linalg.LinAlgError:
                    continue
                A = A - cross @ K
                b = b - K.T @ proj
                self._evidence.setdefault(mid, _Evidence()).add(stamp, 0.5 * (A + A.T), b, p.window)
        return self._judge(stamp, now)

    def _baseline_of(self, mid: int, camera: str, basis: frozenset, stamp: float, res: np.ndarray,
                     position: np.ndarray) -> Optional[np.ndarray]:
        """The pair's offset learnt from its residuals older than the window (None: none yet); queue ``res``.

        A residual joins the baseline once it is ``window`` s old (a plain mean at first, then an
        exponential average over ``baseline_time``), so a move is judged against what the pair showed
        before it. The offset depends on the viewpoint (a calibration error projects differently from
        elsewhere): a baseline is valid within ``baseline_distance`` of the camera positions it was
        learnt at, and starts over beyond. The baseline of a marker declared moved is frozen.
        """
        p = self.params
        key = (mid, camera, basis)
        bl = self._baselines.get(key)
        if bl is None:
            bl = self._baselines[key] = _Baseline()
        bl.pending.append((stamp, res, position))
        frozen = mid in self.moved or mid in self.excluded
        while bl.pending and bl.pending[0][0] < stamp - p.window:
            t, r, pos = bl.pending.popleft()
            if frozen:
                continue
            if bl.value is None or float(np.linalg.norm(pos - bl.position)) > p.baseline_distance:
                bl.value, bl.position, bl.count, bl.stamp = r.copy(), pos.copy(), 1, t
                continue
            bl.count += 1
            alpha = max(1.0 / bl.count, min(1.0, (t - bl.stamp) / p.baseline_time))
            bl.value = bl.value + alpha * (r - bl.value)
            bl.position = bl.position + alpha * (pos - bl.position)
            bl.stamp = t
        if bl.value is None or float(np.linalg.norm(position - bl.position)) > p.baseline_distance:
            return None
        return bl.value

    def _record(self, mid: int, stamp: float, v: _View, k: int, T_map_base: np.ndarray, delta: np.ndarray) -> None:
        # T_base_map' = exp(delta) T_base_map  ->  T_map_cam' = T_map_base exp(-delta) T_base_cam
        T_base_map = geo.se3_perturb(geo.inverse(T_map_base), delta)
        T_map_cam = geo.inverse(v.T_cam_base @ T_base_map)
        q = self._records.setdefault(mid, deque())
        q.append(MarkerObservationRecord(stamp, v.camera, v.px[k], v.model, T_map_cam))
        while q and q[0].stamp < stamp - self.params.remap_window:
            q.popleft()

    def _judge(self, stamp: float, now: float) -> List[MovedMarker]:
        p = self.params
        worst: Optional[Tuple[int, np.ndarray, float]] = None
        for mid, ev in self._evidence.items():
            while ev.items and ev.items[0][0] < stamp - p.window:
                ev.items.popleft()
            if not ev.items:
                continue
            d, T, n = ev.estimate(p.systematic_std)
            self.latest[mid] = (d, T, n)
            if mid in self.moved:
                self.moved[mid].displacement = d
                self.moved[mid].statistic = T
                continue
            if mid in self.excluded:
                continue
            if n >= p.min_observations and T > p.threshold and float(np.linalg.norm(d)) > p.min_move and (
                    worst is None or T > worst[2]):
                worst = (mid, d, T)
            if ev.items[-1][0] == stamp:
                d1, T1, _ = ev.estimate(p.systematic_std, last=True)
                if T1 > p.instant_threshold and float(np.linalg.norm(d1)) > p.min_move and (
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
                self._evidence[other].items.clear()
        q = self._records.get(mid)
        while q and q[0].stamp < stamp:
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
        return list(self._records.get(int(marker_id), ()))

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
            ev.items.clear()


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
