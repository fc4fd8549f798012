"""Marker mapping with the ring: :class:`MapBuilder`.

Feed it ring frames (:meth:`MapBuilder.add_frame`), then :meth:`MapBuilder.build` a
:class:`~aruco_ring_localization.marker_map.MarkerMap`.

**Paper mode** (paper §II-D). Every detected marker gets its single-marker pose ``T_cam_marker``
from IPPE on the mean corners of each (station, camera, marker), refined from the IPPE poses and
their mirrors (:func:`pnp.solve_marker_ippe_undistorted`, both solutions and the ambiguity ratio
kept). The reference marker is the one *closest to its camera with its z axis most parallel to
the camera's axis*: we take the smallest ``distance / cos(angle)`` (angle between the marker's z
and the ray back to the camera's optical axis), among the unambiguous detections of the first
robot placement, unless the user names a ``reference_marker``. Every other marker is chained through
the ring extrinsics, ``T_M0_Mk = T_M0_Ci · T_Ci_Cj · T_Cj_Mk`` (with ``T_Ci_Cj = T_Ci_base ·
T_base_Cj``), averaged over all frames of the placement (translations arithmetically, rotations
by :func:`geometry.average_rotations`). The map frame is then fixed to the reference marker
(:func:`marker_map.map_frame_from_reference`: z up = the robot's z, origin on the floor =
base_link z = 0, x along the reference marker's x made horizontal).

**Beyond the paper.**

* Ambiguity: a detection whose IPPE ambiguity ratio (best/second reprojection error) exceeds
  ``max_ambiguity`` is not used to initialise poses (a flipped pose would corrupt the average).
  A marker seen *only* ambiguously is resolved by consensus across different viewpoints (the
  candidate pose that other views agree with); when nothing agrees it is reported, not mapped.
* Multi-station: frames are grouped into *stations* (robot placements). A station is given by
  the caller, or detected automatically: a frame whose detections moved less than ``still_px``
  from the previous frame's belongs to the same station. Stations enter the map greedily, most
  co-visible mapped markers first; each station's pose is the weighted average of what its
  mapped markers imply, and its new markers are chained from it. Markers never seen together
  with the mapped set (at the same instant, through any camera) are :meth:`unlinked_markers`.
  A few alternating passes then re-average markers over all stations and stations over all
  markers. A marker whose per-station estimates disagree by more than ``max_marker_spread``
  (a wrong ``fiducial_len_override`` size, a marker that moved, the same id printed twice) is
  rejected with a warning.
* ``refined``: the paper initialisation followed by :mod:`bundle_adjustment` over every corner
  of every observation (the paper's future work), with per-marker uncertainty.

Frames: ``W`` is the robot's base frame at the reference station; ``T_W_*`` poses live there
until :meth:`build` expresses them in the map frame.
"""
from __future__ import annotations

import dataclasses
import logging
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Dict, Hashable, List, Optional, Tuple

import numpy as np

from . import geometry as geo
from .config import in_radians, param, section
from .bundle_adjustment import BAOptions, BAProblem, BAResult, bundle_adjust, marker_std_in_frame
from .errors import ArucoRingError, GeometryError, MeasurementError
from .detections import RingFrame
from .marker_map import MarkerEntry, MarkerMap, map_frame_from_reference
from .markers import MarkerSizes
from .camera import CameraModel
from .pnp import MarkerPoseCandidates, solve_marker_ippe_undistorted
from .ring import CameraRing

logger = logging.getLogger(__name__)

METHODS = ("paper", "refined")


@dataclass(frozen=True)
class MappingOptions:
    """Settings of :class:`MapBuilder` (the mapper's ``mapping`` section, config/mapping.yaml)."""

    max_ambiguity: float = param(0.6, "IPPE ambiguity ratio (best/second reprojection error) above which a detection "
                                      "does not initialise a pose (a flipped pose would corrupt the average)")
    max_reprojection_px: float = param(3.0, "detections whose best single-marker pose reprojects worse (RMS) are "
                                            "rejected as bad detections", unit="px")
    max_distance: float = param(12.0, "detections of markers farther than this are ignored", unit="m")
    still_px: float = param(1.5, "automatic stations: consecutive frames whose common detections moved less than "
                                 "this (median of the largest corner motion) belong to one robot placement", unit="px")
    max_frames_per_station: int = param(30, "frames kept per station (more add little and cost time)")
    min_views_for_consensus: int = param(2, "distinct (station, camera) views needed to resolve a marker seen only "
                                            "ambiguously")
    consensus_angle_deg: float = param(10.0, "agreement tolerance of that consensus, rotation", unit="deg")
    consensus_distance: float = param(0.10, "agreement tolerance of that consensus, position", unit="m")
    max_marker_spread: float = param(0.25, "a marker whose per-station positions disagree by more is rejected (a "
                                           "wrong fiducial_len_override, a moved marker, an id printed twice)",
                                     unit="m")
    refine_passes: int = param(3, "alternating marker/station re-averaging passes in multi-station maps")
    refined_reference: bool = param(True, "refined maps without a reference_marker: fix the frame to the marker "
                                          "whose heading the adjustment determines best, not the paper's reference")
    refined_reference_min_stations: int = param(2, "... among markers seen from at least this many stations")
    init_window_stations: int = param(12, "with more stations than this (a hall mapped along a chain of stations) "
                                          "the initialisation adjusts the last this-many stations as it grows")
    init_ba_every: int = param(4, "... every this-many new stations")
    init_calibrate_after: int = param(6, "the ring extrinsics are adjusted during the growth once this many "
                                         "stations are linked (with ba.refine_extrinsics), again each time the "
                                         "linked set doubles")
    init_calibrate_max: int = param(96, "... up to this many stations (all linked stations adjusted)")
    ba: BAOptions = section(BAOptions, "bundle adjustment of method refined; the ring extrinsics are refined too, "
                                       "with priors around the calibration (several stations make them observable)",
                            refine_extrinsics=True)

    consensus_angle = in_radians("consensus_angle_deg")


@dataclass
class _Obs:
    """One detection kept for mapping."""

    station: int
    camera: str
    marker_id: int
    corners: np.ndarray          # (4, 2) raw px
    xy: np.ndarray               # (4, 2) undistorted normalised
    focal: np.ndarray            # (2,) fx, fy px
    T_base_cam: np.ndarray       # extrinsics in force
    model: CameraModel


@dataclass
class _Group:
    """The detections of one marker by one camera at one station, solved on their mean corners.

    Averaging the corners of a still robot divides the noise by sqrt(n) before the single-marker
    pose is solved: single-marker orientations of far markers are weak (the two IPPE solutions
    of a 0.2 m marker at 5 m differ by ~0.1-0.3 px), averaging is what makes them usable.
    """

    station: int
    camera: str
    marker_id: int
    members: List[int]
    candidates: List[np.ndarray]  # T_cam_marker, best first
    errors: List[float]
    ambiguity: float
    distance: float
    cos_facing: float
    T_base_cam: np.ndarray
    xy: np.ndarray                # (4, 2) mean corners, undistorted normalised
    focal: np.ndarray             # (2,) fx, fy px

    def T_base_marker(self, k: int = 0) -> np.ndarray:
        return self.T_base_cam @ self.candidates[k]


# Two candidate poses of one marker closer than this are one (pnp.solve_marker_ippe's mirror mode).
_MIN_SEPARATION = np.radians(1.0)


def _candidates(xy: np.ndarray, size: float, focal: np.ndarray) -> MarkerPoseCandidates:
    """Both poses of the planar ambiguity of one marker from undistorted corners ``xy`` (4, 2),
    refined from the IPPE poses and their mirrors, errors in undistorted px (see
    :func:`pnp.solve_marker_ippe_undistorted`)."""
    return solve_marker_ippe_undistorted(xy, size, focal, mirror=True, min_separation=_MIN_SEPARATION)


def heading_std(T_W_marker: np.ndarray, cov6: np.ndarray) -> float:
    """Standard deviation (rad) of a marker's heading: its x axis made horizontal, about W's z.

    ``cov6`` is the (w, t) covariance of :func:`bundle_adjustment.bundle_adjust` (w a left
    rotation perturbation in W). Infinite when the x axis is vertical.
    """
    x = T_W_marker[:3, 0]
    h2 = float(x[0] ** 2 + x[1] ** 2)
    if h2 < 1e-6:
        return float("inf")
    g = np.array([-x[1], x[0], 0.0]) / h2          # d yaw / d x
    a = np.cross(x, g)                              # d yaw / d w  (dx = w cross x)
    return float(np.sqrt(max(a @ cov6[:3, :3] @ a, 0.0)))


@dataclass
class _Init:
    """The paper-style initialisation over all stations (cached between frames)."""

    reference: Optional[int]
    ref_station: Optional[int]
    T_W_markers: Dict[int, np.ndarray]
    T_W_stations: Dict[int, np.ndarray]
    marker_obs: Dict[int, List[int]]         # marker -> indices of the observations used
    unlinked: List[int]
    rejected: Dict[int, str]
    extrinsics: Dict[str, np.ndarray] = field(default_factory=dict)   # refined during growth


class MapBuilder:
    """Build a marker map from ring frames (see the module docstring).

    Args:
        ring: the calibrated ring (extrinsics used for chaining and as the adjustment's priors;
            intrinsics when a camera frame carries no model); :meth:`set_ring` when tf's arrive.
        sizes: marker side per id.
        method: ``paper`` or ``refined`` (default of :meth:`build`).
        reference_marker: id that fixes the map frame, or None for the paper's rule.
        options: :class:`MappingOptions`.
        frame_id: name of the map frame in the built map.

    Ring frames must hold sanitized detections (:func:`detections.sanitize_observations`, ignored
    ids removed): :class:`pipeline.MappingPipeline` does it once where they enter.
    """

    def __init__(self, ring: CameraRing, sizes: MarkerSizes, method: str = "refined",
                 reference_marker: Optional[int] = None, options: Optional[MappingOptions] = None,
                 frame_id: str = "map"):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.ring = ring
        self.sizes = sizes
        self.method = method
        self.reference_marker = reference_marker
        self.options = options or MappingOptions()
        self.frame_id = frame_id
        self.clear()

    def set_ring(self, ring: CameraRing) -> None:
        """The ring with the extrinsics in force (tf's): used for the frames added from now on and
        as the bundle adjustment's priors."""
        self.ring = ring

    # --- input ------------------------------------------------------------------------------

    def clear(self) -> None:
        """Forget every observation."""
        self._obs: List[_Obs] = []
        self._station_keys: Dict[Hashable, int] = {}
        self._station_frames: List[int] = []
        self._last_corners: Dict[Tuple[str, int], np.ndarray] = {}
        self._last_station: Optional[int] = None
        self.frames = 0
        self.seen: Dict[int, int] = defaultdict(int)          # marker -> detections (all, kept or not)
        self.rejected_detections: Dict[str, int] = defaultdict(int)
        self._version = getattr(self, "_version", 0) + 1
        self._init_cache: Optional[Tuple[int, _Init]] = None
        self._last_groups: List[_Group] = []
        self.last_ba: Optional[BAResult] = None

    @property
    def version(self) -> int:
        """Changes whenever an observation is added (or the builder cleared)."""
        return self._version

    @property
    def station_count(self) -> int:
        return len(self._station_frames)

    def add_frame(self, ring_frame: RingFrame, station: Optional[Hashable] = None) -> int:
        """Add one ring frame; returns the station index it was attributed to (-1: nothing usable).

        Args:
            ring_frame: detections of the ring's cameras at one instant.
            station: any hashable naming the robot placement (frames with the same key share one
                robot pose), or None to detect placements automatically (``still_px``).
        """
        self.frames += 1
        opts = self.options
        detections = []   # (camera, obs, model)
        for name, cam_frame in ring_frame.cameras.items():
            try:
                rc = self.ring[name]
            except KeyError:
                self._reject("unknown camera", name)
                continue
            model = cam_frame.model or rc.model
            for o in cam_frame.observations:
                self.seen[o.marker_id] += 1
                detections.append((name, o, model, rc.T_base_cam))
        if not detections:
            return -1
        st = self._station_for(detections, station)
        self._last_corners = {(name, o.marker_id): o.corners for name, o, _, _ in detections}
        self._last_station = st
        if self._station_frames[st] >= opts.max_frames_per_station:
            return st
        self._station_frames[st] += 1
        for name, o, model, T_base_cam in detections:
            size = self.sizes(o.marker_id)
            xy = model.normalize(o.corners)
            focal = np.array([model.fx, model.fy])
            try:
                cand = solve_marker_ippe_undistorted(xy, size, focal)
                if cand.error > opts.max_reprojection_px:
                    # OpenCV's IPPE can miss small off-axis markers: check with the refined pair first.
                    cand = _candidates(xy, size, focal)
                distance, error = float(np.linalg.norm(cand.T_cam_marker[:3, 3])), cand.error
            except (MeasurementError, GeometryError) as exc:
                self._reject("no pose", name, detail=str(exc))
                continue
            if error > opts.max_reprojection_px:
                self._reject("reprojection", name, detail=f"marker {o.marker_id}: {error:.2f} px")
                continue
            if distance > opts.max_distance:
                self._reject("too far", name)
                continue
            self._obs.append(_Obs(st, name, int(o.marker_id), o.corners, xy, focal, np.array(T_base_cam), model))
        self._version += 1
        return st

    def _reject(self, reason: str, camera: str, n: int = 1, detail: str = "") -> None:
        before = self.rejected_detections[reason]
        self.rejected_detections[reason] += n
        # Log the first of each kind, then every 100th: the caller may feed thousands of frames.
        if before == 0 or (before // 100) != (before + n) // 100:
            logger.warning("mapping: dropped %d detection(s) from %s: %s%s (%d so far)", n, camera, reason,
                           f" ({detail})" if detail else "", before + n)

    def _station_for(self, detections, station: Optional[Hashable]) -> int:
        if station is not None:
            if station not in self._station_keys:
                self._station_keys[station] = len(self._station_frames)
                self._station_frames.append(0)
            return self._station_keys[station]
        if self._last_station is not None:
            moves = []
            for name, o, _, _ in detections:
                prev = self._last_corners.get((name, o.marker_id))
                if prev is not None:
                    moves.append(float(np.max(np.linalg.norm(o.corners - prev, axis=1))))
            if moves and float(np.median(moves)) <= self.options.still_px:
                return self._last_station
        self._station_frames.append(0)
        return len(self._station_frames) - 1

    # --- initialisation (paper's chaining, generalised to several stations) ------------------

    def _groups(self) -> List[_Group]:
        """Detections grouped by (station, camera, marker), solved on their mean corners."""
        members: Dict[Tuple[int, str, int], List[int]] = defaultdict(list)
        for i, o in enumerate(self._obs):
            members[(o.station, o.camera, o.marker_id)].append(i)
        out = []
        for (st, cam, mid), idxs in sorted(members.items()):
            first = self._obs[idxs[0]]
            xy = np.mean([self._obs[i].xy for i in idxs], axis=0)
            try:
                cand = _candidates(xy, self.sizes(mid), first.focal)
            except (MeasurementError, GeometryError):
                continue
            T = cand.T_cam_marker
            dist = float(np.linalg.norm(T[:3, 3]))
            cosf = float(-T[:3, 2] @ (T[:3, 3] / dist))
            out.append(_Group(st, cam, mid, idxs, cand.poses, cand.errors, cand.ambiguity, dist, cosf,
                              first.T_base_cam, xy, first.focal))
        return out

    def _unambiguous(self, g: _Group) -> bool:
        return g.ambiguity <= self.options.max_ambiguity

    def _choose_reference(self, groups: List[_Group]) -> Tuple[Optional[int], Optional[int]]:
        """(reference marker, its station) by the paper's rule, or the user's marker.

        Paper: the marker closest to its camera whose z axis is most parallel to the camera
        axis. Score ``distance / cos(angle)`` (angle between the marker's z and the line of sight),
        lowest wins, among the unambiguous detections of the first placement.
        """
        scored = [(g.distance / max(g.cos_facing, 0.05), g.station, g.marker_id) for g in groups
                  if self._unambiguous(g)]
        if not scored:
            return None, None
        if self.reference_marker is not None:
            mine = [s for s in scored if s[2] == self.reference_marker]
            if not mine:
                return None, None
            best = min(mine)
        else:
            first = min(s[1] for s in scored)
            best = min(s for s in scored if s[1] == first)
        return best[2], best[1]

    def _initialize(self) -> _Init:
        if self._init_cache is not None and self._init_cache[0] == self._version:
            return self._init_cache[1]
        init = self._compute_init()
        self._init_cache = (self._version, init)
        return init

    @staticmethod
    def _station_marker_estimates(groups: List[_Group], usable) -> Dict[int, Dict[int, Tuple[np.ndarray, float]]]:
        """Per station and marker: T_base_marker averaged over the cameras that saw it, and a weight."""
        acc: Dict[Tuple[int, int], List[_Group]] = defaultdict(list)
        for g in groups:
            if usable(g):
                acc[(g.station, g.marker_id)].append(g)
        est: Dict[int, Dict[int, Tuple[np.ndarray, float]]] = defaultdict(dict)
        for (st, mid), gs in acc.items():
            Ts = [g.T_base_marker() for g in gs]
            ws = [len(g.members) / max(g.distance, 0.3) ** 2 for g in gs]
            T = geo.average_transforms(Ts, ws) if len(Ts) > 1 else Ts[0]
            est[st][mid] = (T, float(sum(ws)))
        return est

    def _compute_init(self) -> _Init:
        opts = self.options
        groups = self._groups()
        self._last_groups = groups
        all_ids = sorted({o.marker_id for o in self._obs})
        ref, ref_st = self._choose_reference(groups)
        if ref is None:
            return _Init(None, None, {}, {}, {}, all_ids, {})
        est = self._station_marker_estimates(groups, self._unambiguous)
        # Positions are good even when the orientation is ambiguous: link stations with them too.
        est_pos = self._station_marker_estimates(groups, lambda g: True)
        T_W_s: Dict[int, np.ndarray] = {ref_st: np.eye(4)}
        T_W_m: Dict[int, np.ndarray] = {m: v[0] for m, v in est[ref_st].items()}
        # Long chains of stations (halls): chaining alone drifts (a 0.2 deg calibration error of
        # the ring turns a 40 m hall by degrees), so the growth is interleaved with adjustments:
        # the ring extrinsics are refined once enough stations are linked, and the latest
        # stations are adjusted together every few stations (a sliding window).
        windowed = len(est_pos) > opts.init_window_stations
        calibrated = not (windowed and opts.ba.refine_extrinsics)
        next_calibration = opts.init_calibrate_after
        calib0 = {g.camera: g.T_base_cam for g in groups}
        order = [ref_st]
        since_ba = 0
        init_extr: Dict[str, np.ndarray] = {}
        # Growth in co-visibility order: the station that sees the most mapped markers enters next.
        pending = set(est_pos) - {ref_st}
        while pending:
            links = {s: [m for m in est_pos[s] if m in T_W_m] for s in pending}
            s = max(pending, key=lambda k: (len(links[k]), sum(est_pos[k][m][1] for m in links[k]), -k))
            if not links[s]:
                break
            T_W_s[s] = self._station_pose(est_pos[s], est.get(s, {}), T_W_m, links[s])
            for m, (T, _) in est.get(s, {}).items():
                if m not in T_W_m:
                    T_W_m[m] = T_W_s[s] @ T
            pending.discard(s)
            order.append(s)
            since_ba += 1
            if not windowed:
                continue
            if not calibrated and len(order) >= next_calibration:
                # All linked stations, extrinsics refined; again each time the linked set doubles
                # (up to init_calibrate_max stations): a calibration from the first few stations
                # alone still leaves a bias that the chain accumulates.
                extr = self._init_adjust(groups, order, T_W_m, T_W_s, refine_extrinsics=True, prior=calib0)
                init_extr = dict(extr)
                for g in groups:
                    g.T_base_cam = extr[g.camera]
                est = self._station_marker_estimates(groups, self._unambiguous)
                est_pos = self._station_marker_estimates(groups, lambda g: True)
                since_ba = 0
                next_calibration = 2 * len(order)
                calibrated = next_calibration > opts.init_calibrate_max
            elif len(order) >= opts.init_calibrate_after and since_ba >= opts.init_ba_every:
                self._init_adjust(groups, order[-opts.init_window_stations:], T_W_m, T_W_s)
                since_ba = 0
        if windowed:
            if since_ba:
                self._init_adjust(groups, order[-opts.init_window_stations:], T_W_m, T_W_s)
        else:
            # Alternating re-averaging (no-op with one station): markers over stations, stations
            # over markers.
            if len(T_W_s) > 1:
                for _ in range(opts.refine_passes):
                    T_W_m = self._average_markers(est, T_W_s, T_W_m)
                    for s in T_W_s:
                        if s != ref_st:
                            T_W_s[s] = self._station_pose(est_pos[s], est.get(s, {}), T_W_m,
                                                          [m for m in est_pos[s] if m in T_W_m])
            T_W_m = self._average_markers(est, T_W_s, T_W_m)
        rejected = self._check_spread(est_pos, T_W_s, ref)
        for m in rejected:
            T_W_m.pop(m, None)
        # Markers seen only ambiguously at linked stations: consensus across viewpoints.
        linked_ids = {g.marker_id for g in groups if g.station in T_W_s}
        for mid in all_ids:
            if mid in T_W_m or mid in rejected or mid not in linked_ids:
                continue
            T = self._resolve_by_consensus([g for g in groups if g.marker_id == mid and g.station in T_W_s], T_W_s)
            if T is not None:
                T_W_m[mid] = T
            else:
                rejected[mid] = ("orientation ambiguous (seen nearly face-on or far, from one viewpoint): "
                                 "add a view from another angle")
                logger.warning("mapping: marker %d not mapped: %s", mid, rejected[mid])
        marker_obs: Dict[int, List[int]] = defaultdict(list)
        for i, o in enumerate(self._obs):
            if o.marker_id in T_W_m and o.station in T_W_s:
                marker_obs[o.marker_id].append(i)
        unlinked = [m for m in all_ids if m not in T_W_m and m not in rejected]
        return _Init(ref, ref_st, T_W_m, T_W_s, dict(marker_obs), unlinked, rejected, init_extr)

    def _init_adjust(self, groups: List[_Group], stations: List[int], T_W_m: Dict[int, np.ndarray],
                     T_W_s: Dict[int, np.ndarray], refine_extrinsics: bool = False,
                     prior: Optional[Dict[str, np.ndarray]] = None) -> Dict[str, np.ndarray]:
        """Adjust ``stations`` (first one held fixed) and the markers they see, in place.

        A quick bundle adjustment of the initialisation on the groups' averaged corners (one
        observation per station, camera and marker). Returns the extrinsics per camera name
        (refined when ``refine_extrinsics``, with the usual priors around ``prior``, the
        calibration; the groups' extrinsics are the starting values).
        """
        st_set = set(stations)
        use = [g for g in groups if g.station in st_set and g.marker_id in T_W_m]
        cams = sorted({g.camera for g in groups})
        current = {}
        for g in groups:
            current.setdefault(g.camera, g.T_base_cam)
        calib = {c: (prior or current)[c] for c in cams}
        mids = sorted({g.marker_id for g in use})
        sts = list(stations)
        mi = {m: k for k, m in enumerate(mids)}
        si = {s: k for k, s in enumerate(sts)}
        ci = {c: k for k, c in enumerate(cams)}
        if not use or len(sts) < 2:
            return current
        prob = BAProblem(
            T_W_markers=np.stack([T_W_m[m] for m in mids]),
            sizes=np.array([self.sizes(m) for m in mids]),
            T_W_stations=np.stack([T_W_s[s] for s in sts]),
            T_base_cams=np.stack([calib[c] for c in cams]),
            obs_marker=np.array([mi[g.marker_id] for g in use], dtype=int),
            obs_station=np.array([si[g.station] for g in use], dtype=int),
            obs_camera=np.array([ci[g.camera] for g in use], dtype=int),
            obs_xy=np.stack([g.xy for g in use]),
            obs_focal=np.stack([g.focal for g in use]),
            fixed_marker=None,
            fixed_station=0,
            T_base_cams_start=np.stack([current[c] for c in cams]),
        )
        # A quick adjustment of the growing initialisation: the user's noise, loss and priors,
        # loose tolerances, no covariance.
        res = bundle_adjust(prob, dataclasses.replace(self.options.ba, refine_extrinsics=refine_extrinsics,
                                                      max_nfev=30, ftol=1e-5, xtol=1e-8, gtol=1e-8, lsmr_tol=1e-6,
                                                      covariance=False))
        for k, m in enumerate(mids):
            T_W_m[m] = res.T_W_markers[k]
        for k, s in enumerate(sts):
            T_W_s[s] = res.T_W_stations[k]
        return {c: res.T_base_cams[k] for k, c in enumerate(cams)}

    @staticmethod
    def _station_pose(est_pos_s, est_s, T_W_m, mids) -> np.ndarray:
        """Station pose from its mapped markers.

        The robot drives on the floor, so a station is a planar motion of W (x, y, yaw). With two
        or more markers it is fitted to the marker *centres* (weighted 2D Kabsch): single-marker
        orientations of small, far, face-on markers are uncertain by degrees, their positions by
        millimetres. With one marker its full pose is used (if unambiguous).
        """
        w = np.array([est_pos_s[m][1] for m in mids])
        P = np.array([est_pos_s[m][0][:3, 3] for m in mids])      # in the station's base frame
        Q = np.array([T_W_m[m][:3, 3] for m in mids])             # in W
        if len(mids) == 1 or np.linalg.norm(np.ptp(P[:, :2], axis=0)) < 0.05:
            # One marker (or all on one vertical line): the bearing comes from marker orientations.
            full = [m for m in mids if m in est_s] or list(mids)
            src = est_s if all(m in est_s for m in full) else est_pos_s
            Ts = [T_W_m[m] @ geo.inverse(src[m][0]) for m in full]
            return geo.average_transforms(Ts, [src[m][1] for m in full]) if len(Ts) > 1 else Ts[0]
        keep = np.ones(len(mids), dtype=bool)
        for _ in range(3):
            T = MapBuilder._planar_fit(P[keep], Q[keep], w[keep])
            # Robust: a marker whose mapped position disagrees with the others (a bad link: a
            # wrong size, a moved marker, a flipped pose) is left out and the fit redone.
            res = np.linalg.norm(geo.transform_points(T, P) - Q, axis=1)
            lim = max(0.05, 4.0 * float(np.median(res[keep])))
            new = res <= lim
            if keep.sum() < 3 or np.array_equal(new, keep) or new.sum() < 2:
                break
            keep = new
        return T

    @staticmethod
    def _planar_fit(P: np.ndarray, Q: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Weighted planar (x, y, yaw; z offset) rigid fit ``T`` with ``Q ≈ T · P``; (K, 3) points."""
        wn = w / w.sum()
        pc, qc = wn @ P, wn @ Q
        A, B = P[:, :2] - pc[:2], Q[:, :2] - qc[:2]
        H = (A * wn[:, None]).T @ B
        yaw = float(np.arctan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1]))
        R = geo.rot_z(yaw)
        t = qc - R @ pc
        t[2] = float(wn @ (Q[:, 2] - P[:, 2]))
        return geo.make_transform(R, t)

    @staticmethod
    def _average_markers(est, T_W_s, T_W_m) -> Dict[int, np.ndarray]:
        Ts: Dict[int, List[np.ndarray]] = defaultdict(list)
        ws: Dict[int, List[float]] = defaultdict(list)
        for s, T_ws in T_W_s.items():
            for m, (T, w) in est.get(s, {}).items():
                Ts[m].append(T_ws @ T)
                ws[m].append(w)
        out = dict(T_W_m)
        for m in Ts:
            out[m] = geo.average_transforms(Ts[m], ws[m]) if len(Ts[m]) > 1 else Ts[m][0]
        return out

    def _check_spread(self, est_pos, T_W_s, ref: int) -> Dict[int, str]:
        out: Dict[int, str] = {}
        pos: Dict[int, List[np.ndarray]] = defaultdict(list)
        for s, T_ws in T_W_s.items():
            for m, (T, _) in est_pos.get(s, {}).items():
                pos[m].append((T_ws @ T)[:3, 3])
        for m, ps in pos.items():
            if len(ps) < 2 or m == ref:
                continue
            P = np.array(ps)
            spread = float(np.max(np.linalg.norm(P[:, None] - P[None], axis=-1)))
            if spread > self.options.max_marker_spread:
                out[m] = (f"inconsistent between stations ({1000 * spread:.0f} mm apart): wrong size "
                          f"{self.sizes(m)} m (fiducial_len_override?), moved, or the id is printed twice")
                logger.warning("mapping: marker %d rejected: %s", m, out[m])
        return out

    def _resolve_by_consensus(self, groups: List[_Group], T_W_s: Dict[int, np.ndarray]) -> Optional[np.ndarray]:
        """The candidate orientation that distinct viewpoints agree on, averaged; None if none."""
        opts = self.options
        if len({(g.station, g.camera) for g in groups}) < opts.min_views_for_consensus:
            return None
        cands = [(T_W_s[g.station] @ g.T_base_marker(k), (g.station, g.camera))
                 for g in groups for k in range(len(g.candidates))]

        def agrees(Ta, Tb) -> bool:
            dp, dr = geo.pose_distance(Ta, Tb)
            return dp <= opts.consensus_distance and dr <= opts.consensus_angle

        best, best_support = None, 0
        for Ta, view in cands:
            support = len({v for Tb, v in cands if v != view and agrees(Ta, Tb)})
            if support > best_support:
                best, best_support = Ta, support
        if best is None or best_support + 1 < opts.min_views_for_consensus:
            return None
        members = [Tb for Tb, _ in cands if agrees(best, Tb)]
        return geo.average_transforms(members)

    # --- output -----------------------------------------------------------------------------

    def unlinked_markers(self) -> List[int]:
        """Markers seen but never linked to the mapped set (no common instant with it)."""
        return list(self._initialize().unlinked)

    def rejected_markers(self) -> Dict[int, str]:
        """Markers seen and linked but not mapped, with the reason."""
        return dict(self._initialize().rejected)

    @property
    def reference(self) -> Optional[int]:
        """The reference marker that the current data gives (None before any usable detection)."""
        return self._initialize().reference

    def summary(self) -> Dict[str, Any]:
        """Progress: frames, stations, mapped markers, observations per marker, unlinked, rejected."""
        init = self._initialize()
        per_marker = defaultdict(int)
        for o in self._obs:
            per_marker[o.marker_id] += 1
        return {
            "frames": self.frames,
            "stations": self.station_count,
            "linked_stations": len(init.T_W_stations),
            "reference_marker": init.reference,
            "mapped": sorted(init.T_W_markers),
            "observations": {m: per_marker[m] for m in sorted(per_marker)},
            "unlinked": list(init.unlinked),
            "rejected": dict(init.rejected),
            "rejected_detections": dict(self.rejected_detections),
        }

    def format_summary(self) -> str:
        s = self.summary()
        obs = ", ".join(f"{m}:{n}" for m, n in s["observations"].items() if m in s["mapped"])
        text = (f"{len(s['mapped'])} markers mapped (reference {s['reference_marker']}) from {s['frames']} frames, "
                f"{s['linked_stations']}/{s['stations']} stations; observations per marker {{{obs}}}")
        if s["unlinked"]:
            text += f"; seen but not linked: {s['unlinked']}"
        if s["rejected"]:
            text += f"; rejected: {sorted(s['rejected'])}"
        return text

    def build(self, method: Optional[str] = None) -> MarkerMap:
        """The map (``paper`` or ``refined``; default the builder's method).

        Raises:
            ArucoRingError: no usable detection yet (or the reference marker was never seen).
        """
        method = method or self.method
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        init = self._initialize()
        if init.reference is None:
            if self.reference_marker is not None:
                raise ArucoRingError(f"reference marker {self.reference_marker} was never seen unambiguously")
            raise ArucoRingError("no usable marker detection yet: nothing to map")
        def new_map(ref: int) -> MarkerMap:
            definition = (f"origin on the floor below marker {ref}'s centre, z up, x along marker "
                          f"{ref}'s x made horizontal")
            return MarkerMap(frame_id=self.frame_id, reference_marker=ref, frame_definition=definition,
                             method=method)

        if method == "paper":
            out = new_map(init.reference)
            T_W_map = map_frame_from_reference(init.T_W_markers[init.reference])
            T_map_W = geo.inverse(T_W_map)
            for m, T in init.T_W_markers.items():
                pstd, rstd = self._paper_std(m, init, T_W_map)
                out.add(MarkerEntry(m, T_map_W @ T, self.sizes(m), pstd, rstd, len(init.marker_obs.get(m, []))))
            return out
        res, mids = self._refine(init)
        ref = self._refined_reference(init, res, mids)
        out = new_map(ref)
        # The map frame is fixed to the *refined* reference marker (W's z stays up: the gauge of
        # the adjustment is the robot at the reference station).
        T_W_map = map_frame_from_reference(res.T_W_markers[mids.index(ref)])
        T_map_W = geo.inverse(T_W_map)
        for k, m in enumerate(mids):
            T = res.T_W_markers[k]
            if res.marker_cov is not None:
                pstd, rstd = marker_std_in_frame(res.marker_cov[k], T, T_W_map)
            else:
                pstd, rstd = np.zeros(3), np.zeros(3)
            out.add(MarkerEntry(m, T_map_W @ T, self.sizes(m), pstd, rstd, len(init.marker_obs.get(m, []))))
        if self.options.ba.refine_extrinsics:
            # The markers were estimated through these extrinsics: localizing with them removes the
            # ring's calibration error from every pose (ring_tf publishes them given the map file).
            out.ring_extrinsics = {c: res.T_base_cams[k] for k, c in enumerate(self.ring.names)}
            out.ring_base_frame = self.ring.base_frame
        return out

    def save_map(self, path: str, method: Optional[str] = None, backups: int = 1) -> MarkerMap:
        """Build the map (:meth:`build`) and write it to ``path`` atomically (previous file kept as
        ``<path>.bak``, ``backups`` generations: :meth:`MarkerMap.save`): what the mapper's ``~save_map`` and
        ``save_on_shutdown`` do. A crash at any instant leaves the old file or the new one whole.

        Raises:
            ArucoRingError: nothing to map yet; OSError: the file cannot be written.
        """
        m = self.build(method)
        m.save(path, backups=backups)
        return m

    def _refined_reference(self, init: _Init, res: BAResult, mids: List[int]) -> int:
        """The marker that fixes the refined map's frame.

        The map's yaw is the reference marker's heading (its x axis made horizontal), so the
        frame is only as good as that one marker's orientation: a 0.3 deg error turns the whole
        map (26 mm at 5 m). The paper's rule (near, face-on, first placement) is a proxy for a
        well-determined orientation; after the adjustment the real measure is known, so unless
        the user named a ``reference_marker`` (or ``refined_reference`` is off) the reference is
        the marker whose *heading* has the smallest standard deviation in the adjustment's
        covariance, among markers seen from at least ``refined_reference_min_stations``
        stations when there are any (no truth is involved in the choice).
        """
        if (self.reference_marker is not None or not self.options.refined_reference
                or res.marker_cov is None or len(mids) < 2):
            return init.reference
        stations: Dict[int, set] = defaultdict(set)
        for m, idxs in init.marker_obs.items():
            stations[m] = {self._obs[i].station for i in idxs}
        need = min(self.options.refined_reference_min_stations, max(len(v) for v in stations.values()))
        best, best_std = init.reference, float("inf")
        for k, m in enumerate(mids):
            if len(stations.get(m, ())) < need:
                continue
            std = heading_std(res.T_W_markers[k], res.marker_cov[k])
            if np.isfinite(std) and std < best_std:
                best, best_std = m, std
        if best != init.reference:
            logger.info("mapping: map frame fixed to marker %d (heading std %.3f deg) instead of the paper's "
                        "reference %d", best, np.degrees(best_std), init.reference)
        return best

    def _paper_std(self, m: int, init: _Init, T_W_map: np.ndarray):
        """A documented approximation: the spread of the per-view estimates / sqrt(views).

        With a single view the nominal 1-sigma is 0.05 m / 5 deg (unknown, not zero).
        """
        if m == init.reference:
            return np.zeros(3), np.zeros(3)
        Ts = [init.T_W_stations[g.station] @ g.T_base_marker() for g in self._last_groups
              if g.marker_id == m and g.station in init.T_W_stations and self._unambiguous(g)]
        if len(Ts) < 2:
            return np.full(3, 0.05), np.full(3, np.radians(5.0))
        T_mean = init.T_W_markers[m]
        P = np.array([T[:3, 3] for T in Ts]) @ T_W_map[:3, :3]
        rv = np.array([geo.rvec_from_rotation(T_mean[:3, :3].T @ T[:3, :3]) for T in Ts])
        n = len(Ts)
        return P.std(axis=0, ddof=1) / np.sqrt(n), rv.std(axis=0, ddof=1) / np.sqrt(n)

    def _refine(self, init: _Init) -> Tuple[BAResult, List[int]]:
        mids = sorted(init.T_W_markers)
        sts = sorted(init.T_W_stations)
        cams = self.ring.names
        mi = {m: k for k, m in enumerate(mids)}
        si = {s: k for k, s in enumerate(sts)}
        ci = {c: k for k, c in enumerate(cams)}
        idx = [i for m in mids for i in init.marker_obs.get(m, [])]
        obs = [self._obs[i] for i in idx]
        # Each observation carries the extrinsics in force when it was taken; the solver keeps one
        # per camera: the ring's current one.
        prob = BAProblem(
            T_W_markers=np.stack([init.T_W_markers[m] for m in mids]),
            sizes=np.array([self.sizes(m) for m in mids]),
            T_W_stations=np.stack([init.T_W_stations[s] for s in sts]),
            T_base_cams=np.stack([self.ring[c].T_base_cam for c in cams]),
            obs_marker=np.array([mi[o.marker_id] for o in obs], dtype=int),
            obs_station=np.array([si[o.station] for o in obs], dtype=int),
            obs_camera=np.array([ci[o.camera] for o in obs], dtype=int),
            obs_xy=np.stack([o.xy for o in obs]),
            obs_focal=np.stack([o.focal for o in obs]),
            fixed_marker=None,
            fixed_station=si[init.ref_station],
            T_base_cams_start=np.stack([init.extrinsics.get(c, self.ring[c].T_base_cam) for c in cams]),
        )
        res = bundle_adjust(prob, self.options.ba)
        self.last_ba = res
        return res, mids
