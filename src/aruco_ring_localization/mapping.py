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
  candidate pose that other views agree with, better supported than its rival); when the views
  do not decide it is mapped with the better solution, flagged ``ambiguous`` with a rotation
  uncertainty covering the other one, until another view resolves it.
* Multi-station: frames are grouped into *stations* (ring poses). A station is given by the
  caller, or detected automatically: a frame whose detections moved less than ``still_px`` from
  the station's first frame belongs to it; a moving ring starts a new station once they moved
  ``min_station_motion_px`` (the frames in between are left out). Stations enter the map
  greedily, most co-visible mapped markers first; each station's pose is fitted to its mapped
  markers (planar for a ground robot, SE(3) otherwise: :meth:`MapBuilder._station_model` tests
  the planar prior on the data), and its new markers are chained from it. Markers never seen
  together with the mapped set (at the same instant, through any camera) are
  :meth:`unlinked_markers`. A few alternating passes then re-average markers over all stations
  and stations over all markers. A marker whose per-station estimates disagree by more than
  ``max_marker_spread`` (a wrong ``fiducial_len_override`` size, a marker that moved, the same id
  printed twice) is rejected with a warning.
* ``refined``: the paper initialisation followed by :mod:`bundle_adjustment` over every corner
  of every observation (the paper's future work), with 6-DOF stations and per-marker uncertainty.
* The map frame is ``floor`` (below the reference marker, z up) or ``marker`` (the reference
  marker's own frame), ``MappingOptions.frame``; the map records it, its quality (reprojection
  RMS, stations, station model) and passes :func:`marker_map.check_map` before any save.
* Surveyed frame (``anchors``, :mod:`anchors`): markers with surveyed positions (or one with a
  surveyed pose) define the map frame instead of the reference marker. The initialisation is
  fitted to them (:func:`anchors.fit_frame`, weighted by their std) and the bundle adjustment runs
  in that frame with the anchors as priors and no fixed station (with 2 anchors, or anchors on one
  line, the reference station is held level: the plane is the robot's floor); a paper map is the
  fitted initialisation. The map records each anchor's residual (``anchors``, frame convention
  ``survey``).

Frames: ``W`` is the ring's base frame at the reference station; ``T_W_*`` poses live there
until :meth:`build` expresses them in the map frame.
"""
from __future__ import annotations

import dataclasses
import logging
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Dict, Hashable, List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial.transform import Rotation

from . import geometry as geo
from .anchors import (AnchorSet, Measurements, anchor_report, fit_frame, frame_definition,
                      frame_kind, measurement_report)
from .boards import BoardSet, collapse, expand_covariances, expand_poses, fit_board_pose, loose_priors, solve_board_view
from .bundle_adjustment import (BAOptions, BAProblem, BAResult, MarkerPriors, RelativePoseFactors, bundle_adjust,
                                camera_cov_in_optical_frames, marker_std_in_frame, observation_rms_px)
from .config import in_radians, param, section
from .errors import ArucoRingError, ConfigError, GeometryError, MeasurementError
from .detections import RingFrame, simultaneous_parts
from .mapping_odometry import MappingOdometryOptions, OdometryTrack
from .marker_map import MapSanityLimits, MarkerEntry, MarkerMap, map_frame_from_reference
from .markers import MarkerSizes, marker_corners
from .camera import CameraModel
from .pnp import MarkerPoseCandidates, solve_marker_ippe_undistorted
from .ring import CameraRing

logger = logging.getLogger(__name__)

METHODS = ("paper", "refined")
#: A station needs this many frames (of a camera) before a marker's detection ratio there counts.
RATIO_MIN_FRAMES = 5
#: 1-sigma (rad) of the level prior on the reference station of a frame surveyed by points on one
#: line (2 anchors): the tilt about that line is the robot's floor, as in the reference-marker frame.
LEVEL_SIGMA = 1e-5


FRAMES = ("floor", "marker")
#: ``MappingOptions.extrinsics_prior`` values.
EXTRINSICS_PRIORS = ("options", "ring")
#: The smallest prior std of an extrinsic (rad, m): a ring file's 0 ("exact") holds the camera this
#: tight (TagSLAM's own "fixed", 1e-6).
MIN_EXTRINSICS_SIGMA = 1e-6


@dataclass(frozen=True)
class MappingOptions:
    """Settings of :class:`MapBuilder` (the mapper's ``mapping`` section, config/mapping.yaml)."""

    max_ambiguity: float = param(0.6, "IPPE ambiguity ratio (best/second reprojection error) above which a detection "
                                      "does not initialise a pose (a flipped pose would corrupt the average)")
    max_reprojection_px: float = param(3.0, "detections whose best single-marker pose reprojects worse (RMS) are "
                                            "rejected as bad detections", unit="px")
    max_reprojection_sigmas: float = param(6.0, "... and worse than this many ba.pixel_noise: a corner noise "
                                                "stated above the default 0.5 px raises the limit with it (6: 3 px "
                                                "at 0.5 px, 6 px at TagSLAM's 1 px)")
    max_distance: float = param(12.0, "detections of markers farther than this are ignored", unit="m")
    min_viewing_angle_deg: float = param(0.0, "detections whose line of sight meets the marker's plane at less "
                                              "than this are ignored (grazing views: their corners, and the "
                                              "marker's orientation, are the least certain; TagSLAM's "
                                              "minimum_viewing_angle); 0 keeps all", unit="deg")
    min_marker_area_px: float = param(0.0, "detections whose corners enclose fewer square pixels are ignored "
                                           "(TagSLAM's minimum_tag_area); 0 keeps all", unit="px^2")
    still_px: float = param(1.5, "automatic stations: consecutive frames whose common detections moved less than "
                                 "this (median of the largest corner motion) belong to one robot placement", unit="px")
    still_only: bool = param(False, "automatic stations: a frame is used only when its detections moved at most "
                                    "still_px since the previous frame (the ring at rest): frames taken on the "
                                    "move (motion blur, unsynchronized cameras) are left out. For stop-and-go "
                                    "mapping (drive, stop a second or two, drive on); a ring that never rests "
                                    "(handheld) maps nothing")
    max_frames_per_station: int = param(30, "frames kept per station (more add little and cost time)")
    max_stamp_spread: float = param(0.005, "automatic stations: a ring frame whose cameras' stamps spread wider "
                                           "than this (free-running cameras) and that is not still is split into "
                                           "parts whose cameras were exposed together, each part a frame of its "
                                           "own: a moving ring is at another pose for each part, and one station "
                                           "pose for all of them would bend the map; a negative value keeps "
                                           "every ring frame whole", unit="s")
    min_station_motion_px: float = param(10.0, "automatic stations of a moving ring (handheld, driving): a "
                                               "frame starts a new station only once its detections moved this "
                                               "far (median) from the current station's first frame; frames "
                                               "in between are left out (0: every moving frame is a station)",
                                         unit="px")
    keep_linking_frames: bool = param(True, "automatic stations of a moving ring: a frame that min_station_motion_px "
                                            "would leave out is kept (as a new station) when it sees a marker no "
                                            "kept frame saw, or markers that no kept frame links (seen together, "
                                            "directly or through others): leaving it out would split the map")
    min_views_for_consensus: int = param(2, "distinct (station, camera) views needed to resolve a marker seen only "
                                            "ambiguously")
    consensus_angle_deg: float = param(10.0, "agreement tolerance of that consensus, rotation", unit="deg")
    consensus_distance: float = param(0.10, "agreement tolerance of that consensus, position", unit="m")
    min_detection_ratio: float = param(0.0, "a marker that every camera seeing it detected in fewer than this "
                                            "fraction of its frames at a station (of at least "
                                            f"{RATIO_MIN_FRAMES} frames) is taken for a misread id and not mapped; "
                                            "0 disables")
    max_marker_spread: float = param(0.25, "a marker whose per-station positions disagree by more is rejected (a "
                                           "wrong fiducial_len_override, a moved marker, an id printed twice)",
                                     unit="m")
    max_marker_rms_px: float = param(3.0, "refined maps: a marker still reprojecting worse than this after the "
                                          "adjustment is rejected and the adjustment redone without it", unit="px")
    max_marker_rms_sigmas: float = param(6.0, "... and worse than this many ba.pixel_noise: a corner noise stated "
                                              "above the default 0.5 px (a coarser detector, TagSLAM's pixel_noise) "
                                              "raises the limit with it (6: 3 px at 0.5 px, 12 px at 2 px)")
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
    planar: bool = param(True, "ground robot: the initialisation moves stations in x, y and yaw only (the ring "
                               "base frame's z is up and the floor flat); the bundle adjustment always "
                               "estimates full 6-DOF stations. Turned off automatically, with a warning, when the "
                               "detections show the ring tilting or changing height between stations")
    planar_max_tilt_deg: float = param(5.0, "the planar prior is contradicted when the ring tilts by more than this "
                                            "between stations (median)", unit="deg")
    planar_max_height_change: float = param(0.10, "... or changes height by more than this (median)", unit="m")
    frame: str = param("floor", "map frame: floor = origin on the floor below the reference marker, z up (the "
                                "ring base frame's z), x the marker's x made horizontal; marker = the reference "
                                "marker's own frame (fiducial_slam's convention)")
    surveyed_unseen: bool = param(True, "with anchors: a surveyed marker with a full pose (position and rotation) "
                                        "that the recording never detects is put in the map at its surveyed pose "
                                        "with the survey's std, flagged surveyed_only (it is a marker of the hall "
                                        "the localizer may see later); a position-only one cannot be and is "
                                        "reported as not mapped. false: only detected markers are mapped "
                                        "(build-map --no-surveyed-unseen)")
    extrinsics_prior: str = param("options", "the prior of each camera's extrinsics when the adjustment refines "
                                             "them: options = ba.extrinsics_trans_sigma / extrinsics_rot_sigma_deg "
                                             "for every camera; ring = each camera's extrinsics_std from the ring "
                                             "file (the calibration's own uncertainty, e.g. TagSLAM's camera_poses.yaml "
                                             "R through import-kalibr; 0 holds the camera at its calibration)")
    ba: BAOptions = section(BAOptions, "bundle adjustment of method refined; the ring extrinsics are refined too, "
                                       "with priors around the calibration (several stations make them observable)",
                            refine_extrinsics=True)
    odometry: MappingOdometryOptions = section(MappingOdometryOptions, "the robot's odometry as links between "
                                                                      "consecutive stations of the bundle adjustment "
                                                                      "(long walks: mapping_odometry.py)")
    sanity: MapSanityLimits = section(MapSanityLimits, "checks every map passes before it is saved (a map failing one "
                                                       "is not written, the previous file stays)")

    consensus_angle = in_radians("consensus_angle_deg")
    min_viewing_angle = in_radians("min_viewing_angle_deg")
    planar_max_tilt = in_radians("planar_max_tilt_deg")

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise ConfigError(f"expected one of {', '.join(FRAMES)}, got {self.frame!r}", key="frame")
        if self.extrinsics_prior not in EXTRINSICS_PRIORS:
            raise ConfigError(f"expected one of {', '.join(EXTRINSICS_PRIORS)}, got {self.extrinsics_prior!r}",
                              key="extrinsics_prior")
        for name in ("max_reprojection_px", "max_reprojection_sigmas", "max_marker_rms_px", "max_marker_rms_sigmas"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ConfigError(f"must be a number > 0, got {value!r}", key=name)

    @property
    def reprojection_limit_px(self) -> float:
        """A detection's limit, px (its best single-marker pose's RMS): ``max_reprojection_px``, or
        ``max_reprojection_sigmas`` times ``ba.pixel_noise`` where that is larger (at 3 px alone the
        far tags of TagSLAM's test_11, stated at 1 px, lost 11 detections: map 5.98 against 1.93 mm
        with the scaled limit, 1.58 mm keeping every detection)."""
        return max(float(self.max_reprojection_px), float(self.max_reprojection_sigmas) * float(self.ba.pixel_noise))

    @property
    def marker_rms_limit_px(self) -> float:
        """The per-marker reprojection limit of refined maps, px: ``max_marker_rms_px``, or
        ``max_marker_rms_sigmas`` times ``ba.pixel_noise`` where that is larger (a limit in pixels
        alone would reject the views of a map whose stated corner noise is near it: TagSLAM's test_24
        at 2 px lost the views of 10 tags over 3 px, 1.5 sigma)."""
        return max(float(self.max_marker_rms_px), float(self.max_marker_rms_sigmas) * float(self.ba.pixel_noise))


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
    lens: np.ndarray             # (4, 2, 2) d raw px / d xy at each corner (CameraModel.pixel_jacobian)


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
    lens: np.ndarray              # (4, 2, 2) mean lens Jacobian of the members

    def T_base_marker(self, k: int = 0) -> np.ndarray:
        return self.T_base_cam @ self.candidates[k]


# Two candidate poses of one marker closer than this are one (pnp.solve_marker_ippe's mirror mode).
_MIN_SEPARATION = np.radians(1.0)


def _candidates(xy: np.ndarray, size: float, focal: np.ndarray) -> MarkerPoseCandidates:
    """Both poses of the planar ambiguity of one marker from undistorted corners ``xy`` (4, 2),
    refined from the IPPE poses and their mirrors, errors in undistorted px (see
    :func:`pnp.solve_marker_ippe_undistorted`)."""
    return solve_marker_ippe_undistorted(xy, size, focal, mirror=True, min_separation=_MIN_SEPARATION)


def _area_px(corners: np.ndarray) -> float:
    """Area (px^2) of the quadrilateral of a detection's 4 raw corners (shoelace)."""
    c = np.asarray(corners, dtype=float).reshape(4, 2)
    x, y = c[:, 0], c[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def _viewing_angle(T_cam_marker: np.ndarray) -> float:
    """Angle (rad) between the line of sight to a marker's centre and its plane (90 deg: face-on).
    The same for both poses of the planar ambiguity (they mirror the normal about that line)."""
    t = T_cam_marker[:3, 3]
    return float(np.arcsin(min(1.0, abs(float(T_cam_marker[:3, 2] @ t)) / float(np.linalg.norm(t)))))


def _robust_fit(fit, P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``fit(keep)`` (a transform from the markers flagged in ``keep``), refitted without the
    markers whose centre ``P`` (station frame) lands farther than max(5 cm, 4 x the median) from
    its mapped centre ``Q``: a bad link (a wrong size, a moved marker, a flipped pose)."""
    keep = np.ones(len(P), dtype=bool)
    for _ in range(3):
        T = fit(keep)
        res = np.linalg.norm(geo.transform_points(T, P) - Q, axis=1)
        lim = max(0.05, 4.0 * float(np.median(res[keep])))
        new = res <= lim
        if keep.sum() < 3 or np.array_equal(new, keep) or new.sum() < 2:
            break
        keep = new
    return T


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
    ambiguous: Dict[int, Tuple[float, float]] = field(default_factory=dict)  # id -> (rad, m) between candidates
    planar: bool = True                                                # station model of the initialisation
    station_note: str = ""                                             # why the planar prior was dropped
    #: stations that seeded a group of markers never seen with the others, placed through the surveyed
    #: markers it sees (anchors): station -> the anchors' frame kind there (``pose``, ``points``, ``points_level``)
    seeds: Dict[int, str] = field(default_factory=dict)
    #: markers of a group never seen with the mapped ones that its surveyed markers could not place: why
    unplaced: Dict[int, str] = field(default_factory=dict)


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
        anchors: surveyed markers (:class:`anchors.AnchorSet`) that define the map frame, or None
            (the reference marker's frame).

    Ring frames must hold sanitized detections (:func:`detections.sanitize_observations`, ignored
    ids removed): :class:`pipeline.MappingPipeline` does it once where they enter.
    """

    def __init__(self, ring: CameraRing, sizes: MarkerSizes, method: str = "refined",
                 reference_marker: Optional[int] = None, options: Optional[MappingOptions] = None,
                 frame_id: str = "map", anchors: Optional[AnchorSet] = None, boards: Optional[BoardSet] = None,
                 measurements: Optional[Measurements] = None):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.ring = ring
        self.sizes = sizes
        self.method = method
        self.reference_marker = reference_marker
        self.options = options or MappingOptions()
        self.frame_id = frame_id
        # Survey measurements (distances, planes: :class:`anchors.Measurements`), given or those of
        # the anchors file; a file of measurements only defines no frame (the reference marker's).
        if measurements is None and anchors is not None:
            measurements = anchors.measurements
        self.measurements = measurements if measurements is not None and len(measurements) else None
        if anchors is not None and not anchors.anchors:
            anchors = None
        if self.measurements is not None and self.measurements.planes and anchors is None:
            raise ConfigError("a plane is given in the surveyed frame: it needs anchors that define that frame",
                              path=self.measurements.source, key=self.measurements.planes[0].key)
        self.anchors = anchors
        self.boards = boards
        self.clear()

    def set_ring(self, ring: CameraRing) -> None:
        """The ring with the extrinsics in force (tf's): used for the frames added from now on and
        as the bundle adjustment's priors."""
        self.ring = ring

    def recalibrate(self, ring: CameraRing) -> None:
        """A new calibration of the ring (the mapper's calibration from rough values): the extrinsics
        of every observation kept so far are replaced by ``ring``'s, as if they had been in force
        when it was added, and the frames added from now on use them too."""
        self.ring = ring
        for o in self._obs:
            if o.camera in ring.names:
                o.T_base_cam = np.array(ring[o.camera].T_base_cam)
        self._init_cache = None
        self._last_groups = []
        self._version += 1

    # --- input ------------------------------------------------------------------------------

    def clear(self) -> None:
        """Forget every observation."""
        self._obs: List[_Obs] = []
        self._station_keys: Dict[Hashable, int] = {}
        self._station_frames: List[int] = []
        self._station_stamps: List[float] = []                               # stamp of each station's first frame
        self._frame_stamps: List[float] = []       # every ring frame (part) added: odometry message_sampling frames
        self.odometry = OdometryTrack()                                       # mapping.odometry's poses
        self._camera_frames: Dict[Tuple[int, str], int] = defaultdict(int)   # (station, camera) -> frames kept
        self._anchor_corners: Dict[Tuple[str, int], np.ndarray] = {}
        self._previous_corners: Dict[Tuple[str, int], np.ndarray] = {}     # still_only: the last frame's
        self._links: Dict[int, int] = {}       # union-find of the markers linked by the kept frames
        self._last_station: Optional[int] = None
        self.frames = 0
        #: frames left out because the ring was moving but had not moved min_station_motion_px yet
        #: (with still_only: because it moved since the previous frame).
        self.skipped_moving = 0
        self.seen: Dict[int, int] = defaultdict(int)          # marker -> detections (all, kept or not)
        self.rejected_detections: Dict[str, int] = defaultdict(int)
        self._version = getattr(self, "_version", 0) + 1
        self._init_cache: Optional[Tuple[int, _Init]] = None
        self._last_groups: List[_Group] = []
        #: (station, camera, marker) -> (detections, their candidates) of the last build (_groups).
        self._group_candidates: Dict[Tuple[int, str, int], Tuple[int, Optional[MarkerPoseCandidates]]] = {}
        self._warned: Dict[int, str] = {}      # marker -> the kind of reason last warned about
        self.last_ba: Optional[BAResult] = None
        self._refine_rejected: Tuple[int, Dict[int, str]] = (-1, {})

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
                robot pose), or None to detect placements automatically (``still_px``,
                ``min_station_motion_px``).
        """
        self.frames += 1
        if station is None and self.options.still_only:
            if not self._at_rest(ring_frame):
                self.skipped_moving += 1
                self._frame_stamps.append(float(ring_frame.stamp))
                return -1
            return self._add_part(ring_frame)
        if station is None and self.options.max_stamp_spread >= 0 and len(ring_frame.cameras) > 1:
            stamps = [cf.stamp for cf in ring_frame.cameras.values()]
            if max(stamps) - min(stamps) > self.options.max_stamp_spread and not self._still(ring_frame):
                kept = [self._add_part(part) for part in simultaneous_parts(ring_frame, self.options.max_stamp_spread)]
                return max(kept)
        return self._add_part(ring_frame, station)

    def _still(self, ring_frame: RingFrame) -> bool:
        """Whether ``ring_frame``'s detections moved at most ``still_px`` from the current station's
        first frame (:meth:`_median_move`)."""
        if self._last_station is None:
            return False
        move = self._median_move((name, o) for name, cf in ring_frame.cameras.items() for o in cf.observations)
        return move is not None and move <= self.options.still_px

    def _at_rest(self, ring_frame: RingFrame) -> bool:
        """``still_only``: whether ``ring_frame``'s detections moved at most ``still_px`` since the
        previous frame (False for the first frame and when no marker is in both)."""
        pairs = [(name, o) for name, cf in ring_frame.cameras.items() for o in cf.observations]
        move = self._median_move(pairs, self._previous_corners)
        self._previous_corners = {(name, o.marker_id): o.corners for name, o in pairs}
        return move is not None and move <= self.options.still_px

    def _median_move(self, detections, reference: Optional[Dict[Tuple[str, int], np.ndarray]] = None
                     ) -> Optional[float]:
        """Median over ``detections`` ((camera, observation) pairs) of each one's largest corner motion
        since ``reference`` (default: the current station's first frame), px; None when none of them
        is in it."""
        ref = self._anchor_corners if reference is None else reference
        moves = [float(np.max(np.linalg.norm(o.corners - prev, axis=1)))
                 for name, o in detections for prev in [ref.get((name, o.marker_id))]
                 if prev is not None]
        return float(np.median(moves)) if moves else None

    def _add_part(self, ring_frame: RingFrame, station: Optional[Hashable] = None) -> int:
        opts = self.options
        self._frame_stamps.append(float(ring_frame.stamp))
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
        if st < 0:
            self.skipped_moving += 1
            return -1
        while len(self._station_stamps) < len(self._station_frames):
            self._station_stamps.append(float(ring_frame.stamp))
        if self._station_frames[st] >= opts.max_frames_per_station:
            return st
        self._station_frames[st] += 1
        for name in ring_frame.cameras:
            self._camera_frames[(st, name)] += 1
        limit = opts.reprojection_limit_px
        for name, o, model, T_base_cam in detections:
            size = self.sizes(o.marker_id)
            xy = model.normalize(o.corners)
            focal = np.array([model.fx, model.fy])
            try:
                cand = solve_marker_ippe_undistorted(xy, size, focal)
                if cand.error > limit:
                    # OpenCV's IPPE can miss small off-axis markers: check with the refined pair first.
                    cand = _candidates(xy, size, focal)
                distance, error = float(np.linalg.norm(cand.T_cam_marker[:3, 3])), cand.error
            except (MeasurementError, GeometryError) as exc:
                self._reject("no pose", name, detail=str(exc))
                continue
            if error > limit:
                self._reject("reprojection", name, detail=f"marker {o.marker_id}: {error:.2f} px")
                continue
            if distance > opts.max_distance:
                self._reject("too far", name)
                continue
            if opts.min_marker_area_px > 0 and _area_px(o.corners) < opts.min_marker_area_px:
                self._reject("too small", name)
                continue
            if opts.min_viewing_angle_deg > 0 and _viewing_angle(cand.T_cam_marker) < opts.min_viewing_angle:
                self._reject("grazing view", name)
                continue
            self._obs.append(_Obs(st, name, int(o.marker_id), o.corners, xy, focal, np.array(T_base_cam), model,
                                  model.pixel_jacobian(xy)))
        kept = sorted({int(o.marker_id) for _, o, _, _ in detections})
        for a, b in zip(kept, kept[1:] + kept[:1]):
            self._links[self._link_root(a)] = self._link_root(b)
        self._version += 1
        return st

    def _link_root(self, m: int) -> int:
        while self._links.setdefault(m, m) != m:
            self._links[m] = self._links[self._links[m]]
            m = self._links[m]
        return m

    def _brings_links(self, detections) -> bool:
        """Whether a frame sees a marker no kept frame saw, or markers the kept frames do not link."""
        ids = {int(o.marker_id) for _, o, _, _ in detections}
        if any(m not in self._links for m in ids):
            return True
        return len({self._link_root(m) for m in ids}) > 1

    def add_odometry(self, stamp: float, T_odom_body: np.ndarray) -> bool:
        """One odometry pose (``mapping.odometry``: the odometry body in its odom frame at ``stamp``);
        consecutive stations are linked by the motion between them. False when it is not a finite
        rigid transform (ignored)."""
        ok = self.odometry.add(stamp, T_odom_body)
        if ok:
            self._version += 1
        return ok

    def set_odometry(self, stamps: Sequence[float], poses: np.ndarray) -> int:
        """Replace the odometry by these poses (:meth:`add_odometry` each); returns how many were kept."""
        self.odometry = OdometryTrack(stamps, poses)
        self._version += 1
        return len(self.odometry)

    def _odometry_factors(self, stations: Sequence[int], index: Dict[int, int]) -> Optional[RelativePoseFactors]:
        """Odometry links between consecutive ``stations`` (by stamp), station indices mapped through
        ``index`` (station -> the problem's station index); None without odometry."""
        if len(self.odometry) < 2:
            return None
        links = self.odometry.links({s: self._station_stamps[s] for s in stations if s < len(self._station_stamps)},
                                    self.options.odometry, frame_stamps=self._frame_stamps)
        if links is None:
            return None
        return RelativePoseFactors([index[s] for s in links.station_i], [index[s] for s in links.station_j],
                                   links.T_ij, links.sigma, robust_scale=links.robust_scale)

    def _odometry_bridge(self, pending, T_W_s: Dict[int, np.ndarray]) -> Optional[Tuple[int, np.ndarray]]:
        """A pending station that no mapped marker links, placed by the odometry from the placed
        station nearest in time (``(station, T_W_station)``), or None (no odometry covers one)."""
        if len(self.odometry) < 2 or not T_W_s:
            return None
        opts = self.options.odometry
        X = opts.T_base_odom
        placed = sorted(T_W_s, key=lambda k: self._station_stamps[k])
        stamps = np.array([self._station_stamps[k] for k in placed])
        best = None
        for s in pending:
            t = self._station_stamps[s]
            k = int(np.argmin(np.abs(stamps - t)))
            gap = abs(stamps[k] - t)
            if best is None or gap < best[0]:
                best = (gap, s, placed[k])
        if best is None:
            return None
        _, s, p = best
        P_s = self.odometry.pose_at(self._station_stamps[s], opts.max_gap)
        P_p = self.odometry.pose_at(self._station_stamps[p], opts.max_gap)
        if P_s is None or P_p is None:
            return None
        return s, T_W_s[p] @ X @ geo.inverse(P_p) @ P_s @ geo.inverse(X)

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
            # Motion of the detections since the first frame of the current station.
            move = self._median_move((name, o) for name, o, _, _ in detections)
            if move is not None:
                if move <= self.options.still_px:
                    return self._last_station
                if move < self.options.min_station_motion_px and not (self.options.keep_linking_frames
                                                                      and self._brings_links(detections)):
                    return -1       # moving, but still close to the last station: adds little
        self._station_frames.append(0)
        self._anchor_corners = {(name, o.marker_id): o.corners for name, o, _, _ in detections}
        self._last_station = len(self._station_frames) - 1
        return self._last_station

    # --- initialisation (paper's chaining, generalised to several stations) ------------------

    def _groups(self) -> List[_Group]:
        """Detections grouped by (station, camera, marker), solved on their mean corners."""
        members: Dict[Tuple[int, str, int], List[int]] = defaultdict(list)
        for i, o in enumerate(self._obs):
            members[(o.station, o.camera, o.marker_id)].append(i)
        out = []
        for key, idxs in sorted(members.items()):
            st, cam, mid = key
            first = self._obs[idxs[0]]
            xy = np.mean([self._obs[i].xy for i in idxs], axis=0)
            # A group's detections only grow (clear() forgets them): the same count is the same
            # corners, solved at an earlier build (the live mapper rebuilds every few seconds).
            cached = self._group_candidates.get(key)
            if cached is not None and cached[0] == len(idxs):
                cand = cached[1]
            else:
                try:
                    cand = _candidates(xy, self.sizes(mid), first.focal)
                except (MeasurementError, GeometryError):
                    cand = None
                self._group_candidates[key] = (len(idxs), cand)
            if cand is None:
                continue
            T = cand.T_cam_marker
            dist = float(np.linalg.norm(T[:3, 3]))
            cosf = float(-T[:3, 2] @ (T[:3, 3] / dist))
            lens = np.mean([self._obs[i].lens for i in idxs], axis=0)
            out.append(_Group(st, cam, mid, idxs, cand.poses, cand.errors, cand.ambiguity, dist, cosf,
                              first.T_base_cam, xy, first.focal, lens))
        if self.boards is not None and len(self.boards):
            self._board_views(out, self.boards)
        return out

    def _board_views(self, groups: List[_Group], boards: BoardSet) -> None:
        """Markers of one board seen together by one camera at one station: each one's pose from
        the board's (:func:`boards.solve_board_view`, all their corners at once), unambiguous (in
        place). A marker that does not fit its board's view (over
        :attr:`MappingOptions.reprojection_limit_px`) keeps its own single-marker solution; a view
        that does not fit at all is left alone."""
        views: Dict[Tuple[int, str, int], List[_Group]] = defaultdict(list)
        for g in groups:
            b = boards.board_of(g.marker_id)
            if b is not None:
                views[(g.station, g.camera, b)].append(g)
        lim = self.options.reprojection_limit_px
        for (_, _, b), gs in views.items():
            if len(gs) < 2:
                continue
            board = boards.boards[b]
            for _ in range(2):
                try:
                    T_cb, rms, per = solve_board_view(board, [(g.marker_id, g.xy, self.sizes(g.marker_id), g.candidates)
                                                             for g in gs], gs[0].focal)
                except GeometryError:
                    break
                fit = [g for g in gs if per[g.marker_id] <= lim]
                if len(fit) == len(gs) or len(fit) < 2:
                    break
                gs = fit
            else:
                continue
            if len([g for g in gs if per[g.marker_id] <= lim]) < 2:
                continue
            for g in gs:
                if per[g.marker_id] > lim:
                    continue
                T = T_cb @ board.layout[g.marker_id]
                g.candidates = [T]
                g.errors = [per[g.marker_id]]
                g.ambiguity = 0.0
                g.distance = float(np.linalg.norm(T[:3, 3]))
                g.cos_facing = float(-T[:3, 2] @ (T[:3, 3] / g.distance))

    def _unambiguous(self, g: _Group) -> bool:
        return g.ambiguity <= self.options.max_ambiguity

    def _choose_reference(self, groups: List[_Group]) -> Tuple[Optional[int], Optional[int]]:
        """(reference marker, its station) by the paper's rule, or the user's marker.

        Paper: the marker closest to its camera whose z axis is most parallel to the camera
        axis. Score ``distance / cos(angle)`` (angle between the marker's z and the line of sight),
        lowest wins, among the unambiguous detections of the first placement *of the largest
        co-visibility component* (markers linked through stations that saw them together): when the
        data fall apart into groups never seen together, the map is the largest one, not whichever
        the first frame happened to see.
        """
        comp = self._main_component(groups)
        scored = [(g.distance / max(g.cos_facing, 0.05), g.station, g.marker_id) for g in groups
                  if self._unambiguous(g) and (self.reference_marker is not None or g.marker_id in comp)]
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

    @staticmethod
    def _largest_component(groups: List[_Group]) -> set:
        """Marker ids of the largest set linked by co-visibility (seen at a common station)."""
        comps = MapBuilder._components(groups)
        return comps[0] if comps else set()

    def _main_component(self, groups: List[_Group]) -> set:
        """The co-visibility component the map grows from: the largest one; with anchors, the largest
        whose own surveyed markers fix a frame (a surveyed pose or 3 positions off one line, else 2
        positions), so that the other groups can be placed through theirs (:meth:`_anchor_seed`)."""
        comps = self._components(groups)
        if self.anchors is not None:
            kinds = [self._anchor_kind(c) for c in comps]
            for wanted in (("pose", "points"), ("points_level",)):
                for c, k in zip(comps, kinds):
                    if k in wanted:
                        return c
        return comps[0] if comps else set()

    def _anchor_kind(self, ids) -> Optional[str]:
        """:func:`anchors.frame_kind` of the anchors among marker ``ids``; None when they fix no frame."""
        assert self.anchors is not None
        try:
            return frame_kind(self.anchors.subset(ids))
        except ConfigError:
            return None

    @staticmethod
    def _components(groups: List[_Group]) -> List[set]:
        """Marker ids of the sets linked by co-visibility (seen at a common station), largest first."""
        parent: Dict[int, int] = {}

        def find(a: int) -> int:
            while parent.setdefault(a, a) != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        by_station: Dict[int, set] = defaultdict(set)
        for g in groups:
            by_station[g.station].add(g.marker_id)
            find(g.marker_id)
        for ids in by_station.values():
            ids = sorted(ids)
            for a, b in zip(ids, ids[1:]):
                parent[find(a)] = find(b)
        comps: Dict[int, set] = defaultdict(set)
        for m in parent:
            comps[find(m)].add(m)
        return sorted(comps.values(), key=lambda c: (-len(c), min(c)))

    def _initialize(self) -> _Init:
        if self._init_cache is not None and self._init_cache[0] == self._version:
            return self._init_cache[1]
        init = self._compute_init()
        self._init_cache = (self._version, init)
        # Once per marker and kind of reason (the numbers in it change), not at every rebuild.
        kinds = {m: why.split(" (")[0] for m, why in init.rejected.items()}
        for m, why in init.rejected.items():
            if self._warned.get(m) != kinds[m]:
                logger.warning("mapping: marker %d not mapped: %s", m, why)
        self._warned = kinds
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
        all_ids = sorted({o.marker_id for o in self._obs})
        misread = self._misread(groups)
        groups = [g for g in groups if g.marker_id not in misread]
        self._last_groups = groups
        ref, ref_st = self._choose_reference(groups)
        if ref is None:
            return _Init(None, None, {}, {}, {}, [m for m in all_ids if m not in misread], misread)
        est = self._station_marker_estimates(groups, self._unambiguous)
        # Positions are good even when the orientation is ambiguous: link stations with them too.
        est_pos = self._station_marker_estimates(groups, lambda g: True)
        planar, note = self._station_model(est)
        T_W_s: Dict[int, np.ndarray] = {ref_st: np.eye(4)}
        T_W_m: Dict[int, np.ndarray] = {m: v[0] for m, v in est[ref_st].items()}
        # Long chains of stations (halls): chaining alone drifts (a 0.2 deg calibration error of
        # the ring turns a 40 m hall by degrees), so the growth is interleaved with adjustments:
        # the ring extrinsics are refined once enough stations are linked, and the latest
        # stations are adjusted together every few stations (a sliding window).
        # Not for a rig that keeps seeing the same markers from stations far apart in time (moving
        # about a room): there the alternating re-averaging below is enough, and windows are costly.
        windowed = len(est_pos) > opts.init_window_stations and not self._revisits(est_pos, sorted(est_pos))
        calibrated = not (windowed and self._refines_extrinsics)
        next_calibration = opts.init_calibrate_after
        calib0 = {g.camera: g.T_base_cam for g in groups}
        order = [ref_st]
        since_ba = 0
        init_extr: Dict[str, np.ndarray] = {}
        # Groups of markers never seen with the mapped ones, seeded from the anchors they hold
        # (station -> frame kind); the windowed adjustments stay inside one group (group_start), the
        # calibration uses the first group (order[:main_end]).
        seeds: Dict[int, str] = {}
        T_map_W: Optional[np.ndarray] = None
        group_start, main_end = 0, None
        # Growth in co-visibility order: the station that sees the most mapped markers enters next.
        pending = set(est_pos) - {ref_st}
        while pending:
            links = {s: [m for m in est_pos[s] if m in T_W_m] for s in pending}
            s = max(pending, key=lambda k: (len(links[k]), sum(est_pos[k][m][1] for m in links[k]), -k))
            if links[s]:
                T_W_s[s] = self._station_pose(est_pos[s], est.get(s, {}), T_W_m, links[s], planar)
            else:
                # No station left that sees a mapped marker: the rest are groups never seen with the
                # mapped markers. With anchors, a station that sees enough of a group's surveyed
                # markers to fix its own pose is placed where the survey has them, and the growth
                # goes on from it through that group; else the odometry (mapping.odometry) places the
                # pending station nearest in time to a placed one; without either the map ends here.
                seed = None
                if self.anchors is not None:
                    if T_map_W is None:
                        T_map_W = self._anchor_frame(T_W_m)
                    if T_map_W is not None:
                        seed = self._anchor_seed(pending, est, est_pos, T_map_W, planar)
                if seed is not None:
                    s, T_W_s[s], seeds[s] = seed
                    group_start = len(order)
                    main_end = len(order) if main_end is None else main_end
                else:
                    bridged = self._odometry_bridge(pending, T_W_s)
                    if bridged is None:
                        break
                    s, T_W_s[s] = bridged
            for m, (T, _) in est.get(s, {}).items():
                if m not in T_W_m:
                    T_W_m[m] = T_W_s[s] @ T
            pending.discard(s)
            order.append(s)
            since_ba += 1
            if not windowed:
                continue
            if not calibrated and len(order[:main_end]) >= next_calibration:
                # All linked stations, extrinsics refined; again each time the linked set doubles
                # (up to init_calibrate_max stations): a calibration from the first few stations
                # alone still leaves a bias that the chain accumulates.
                extr = self._init_adjust(groups, order[:main_end], T_W_m, T_W_s, refine_extrinsics=True,
                                         prior=calib0)
                init_extr = dict(extr)
                for g in groups:
                    g.T_base_cam = extr[g.camera]
                est = self._station_marker_estimates(groups, self._unambiguous)
                est_pos = self._station_marker_estimates(groups, lambda g: True)
                since_ba = 0
                next_calibration = 2 * len(order[:main_end])
                calibrated = next_calibration > opts.init_calibrate_max
            elif len(order) >= opts.init_calibrate_after and since_ba >= opts.init_ba_every:
                self._init_adjust(groups, order[max(group_start, len(order) - opts.init_window_stations):], T_W_m,
                                  T_W_s)
                since_ba = 0
        if windowed and since_ba:
            self._init_adjust(groups, order[max(group_start, len(order) - opts.init_window_stations):], T_W_m, T_W_s)
        if not windowed or self._revisits(est_pos, order):
            # Alternating re-averaging (no-op with one station): markers over stations, stations
            # over markers. After a windowed growth too when stations far apart in the growth
            # order see the same markers (a hall driven twice): the window adjustments moved
            # markers that earlier stations, outside the window, see.
            if len(T_W_s) > 1:
                for _ in range(opts.refine_passes):
                    T_W_m = self._average_markers(est, T_W_s, T_W_m)
                    for s in T_W_s:
                        if s != ref_st:
                            T_W_s[s] = self._station_pose(est_pos[s], est.get(s, {}), T_W_m,
                                                          [m for m in est_pos[s] if m in T_W_m], planar)
            T_W_m = self._average_markers(est, T_W_s, T_W_m)
        rejected = {**misread, **self._check_spread(est_pos, T_W_s, ref, ref_st, T_W_m, planar)}
        for m in rejected:
            T_W_m.pop(m, None)
        # Markers seen only ambiguously at linked stations: consensus across viewpoints; when the
        # views do not decide (one viewpoint), the better solution with a large uncertainty.
        linked_ids = {g.marker_id for g in groups if g.station in T_W_s}
        ambiguous: Dict[int, Tuple[float, float]] = {}
        for mid in all_ids:
            if mid in T_W_m or mid in rejected or mid not in linked_ids:
                continue
            mine = [g for g in groups if g.marker_id == mid and g.station in T_W_s]
            T = self._resolve_by_consensus(mine, T_W_s)
            if T is not None:
                T_W_m[mid] = T
                continue
            T_W_m[mid], ambiguous[mid] = self._better_solution(mine, T_W_s)
            logger.info("mapping: marker %d mapped with its better IPPE solution (orientation ambiguous from "
                        "one viewpoint: the two solutions differ by %.1f deg); another view resolves it", mid,
                        np.degrees(ambiguous[mid][0]))
        marker_obs: Dict[int, List[int]] = defaultdict(list)
        for i, o in enumerate(self._obs):
            if o.marker_id in T_W_m and o.station in T_W_s:
                marker_obs[o.marker_id].append(i)
        unlinked = [m for m in all_ids if m not in T_W_m and m not in rejected]
        unplaced = self._unplaced(groups, unlinked, planar) if self.anchors is not None else {}
        return _Init(ref, ref_st, T_W_m, T_W_s, dict(marker_obs), unlinked, rejected, init_extr, ambiguous,
                     planar, note, seeds=seeds, unplaced=unplaced)

    def _anchor_frame(self, T_W_m: Dict[int, np.ndarray]) -> Optional[np.ndarray]:
        """``T_map_W`` of the surveyed frame fitted to the anchors mapped so far (None: too few)."""
        assert self.anchors is not None
        if self._anchor_kind(list(T_W_m)) is None:
            return None
        return fit_frame(self.anchors, T_W_m).T_map_W

    def _anchor_seed(self, pending, est, est_pos, T_map_W: np.ndarray,
                     planar: bool) -> Optional[Tuple[int, np.ndarray, str]]:
        """A station of a group never seen with the mapped markers, placed through the surveyed markers it
        sees: ``(station, T_W_station, frame kind)``, or None when no pending station sees enough of them.

        The station's own view of its surveyed markers is fitted to the survey (:func:`anchors.fit_frame`,
        weighted by the std): one surveyed pose (its orientation only from an unambiguous view: a
        mirrored pose would turn the whole group), or 3 surveyed positions off one line; 2 positions
        only for a ground robot (``planar``: the station's z is the floor's). Among the stations that
        can, the one whose surveyed markers it sees best (detections / distance^2) seeds.
        """
        assert self.anchors is not None
        by_id = {a.marker_id: a for a in self.anchors.anchors}
        best = None
        for s in pending:
            seen = [m for m in est_pos[s] if m in by_id]
            if not seen:
                continue
            clear = est.get(s, {})
            usable = [by_id[m] if (by_id[m].rotation is None or m in clear)
                      else dataclasses.replace(by_id[m], rotation=None, rotation_std=None) for m in seen]
            try:
                sub = AnchorSet(usable, self.anchors.frame_id, self.anchors.source)
            except ConfigError:
                continue
            kind = frame_kind(sub)
            if kind == "points_level" and not planar:
                continue
            key = (kind == "points_level", -sum(est_pos[s][m][1] for m in seen), s)
            if best is None or key < best[0]:
                best = (key, s, sub, kind)
        if best is None:
            return None
        _, s, sub, kind = best
        T_s_m = {m: (est[s][m][0] if m in est.get(s, {}) else est_pos[s][m][0]) for m in sub.ids}
        T_W_s = geo.inverse(T_map_W) @ fit_frame(sub, T_s_m).T_map_W
        if planar:   # a ground robot's station moves in W's plane
            T_W_s = geo.make_transform(geo.rot_z(float(np.arctan2(T_W_s[1, 0], T_W_s[0, 0]))), T_W_s[:3, 3])
        logger.info("mapping: station %d (it sees markers %s, never seen with the mapped ones) placed through the "
                    "surveyed marker(s) %s (%s)", s, sorted(est_pos[s]), sub.ids, kind)
        return s, T_W_s, kind

    def _unplaced(self, groups: List[_Group], unlinked: List[int], planar: bool) -> Dict[int, str]:
        """Why each marker of ``unlinked`` stayed out of a map with anchors: its group (markers seen
        together) holds no surveyed marker, or too few to fix the group's pose from one station."""
        assert self.anchors is not None
        left = set(unlinked)
        out: Dict[int, str] = {}
        for c in self._components(groups):
            if not c & left:
                continue
            surveyed = sorted(set(self.anchors.ids) & c)
            group = sorted(c)
            if surveyed:
                why = (f"its group {group} is never seen together with the mapped markers, and no single view of "
                       f"its surveyed markers {surveyed} fixes the group's pose (that takes one surveyed pose seen "
                       f"unambiguously, or 3 surveyed positions off one line"
                       f"{', or 2 for a ground robot' if planar else ''}, in one station's view): survey more of "
                       f"them, or map so that the group is seen with the others")
            else:
                why = (f"its group {group} is never seen together with the mapped markers and holds no surveyed "
                       f"marker ({self.anchors.source}): map so that it is, or survey one of them")
            for m in c & left:
                out[m] = why
        return out

    def _revisits(self, est_pos, order: List[int]) -> bool:
        """Whether some marker is seen from stations more than two windows apart in ``order``
        (time, or the growth order): not a chain of stations along a hall."""
        w = self.options.init_window_stations
        rank = {s: k for k, s in enumerate(order)}
        first: Dict[int, int] = {}
        last: Dict[int, int] = {}
        for s in order:
            for m in est_pos.get(s, {}):
                first.setdefault(m, rank[s])
                last[m] = rank[s]
        return any(last[m] - first[m] > 2 * w for m in first)

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
            obs_lens=np.stack([g.lens for g in use]),
            fixed_marker=None,
            fixed_station=0,
            T_base_cams_start=np.stack([current[c] for c in cams]),
            odometry=self._odometry_factors(sts, si),
            extrinsics_sigma=self._extrinsics_sigma(cams),
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

    def _station_model(self, est) -> Tuple[bool, str]:
        """(planar, note): whether the initialisation may use the ground robot's planar prior.

        Data test, no chaining needed: a ring that only drives on a flat floor (x, y, yaw) sees
        every marker at the same *elevation* in its base frame at every station: the base's z axis
        expressed in the marker frame, and the marker's height above the base, do not change. The
        medians over all (marker, station) pairs of the change of the first (angle) and of the
        second (m) are compared with ``planar_max_tilt`` / ``planar_max_height_change``.
        """
        opts = self.options
        if not opts.planar:
            return False, "planar prior off (planar: false)"
        tilts, heights = [], []
        per_marker: Dict[int, List[Tuple[np.ndarray, float]]] = defaultdict(list)
        for st, markers in est.items():
            for m, (T, _) in markers.items():
                per_marker[m].append((T[:3, :3].T[:, 2], float(T[2, 3])))
        for m, vals in per_marker.items():
            if len(vals) < 2:
                continue
            U = np.array([v[0] for v in vals])
            u = np.median(U, axis=0)
            u /= max(float(np.linalg.norm(u)), 1e-12)
            tilts.extend(np.arccos(np.clip(U @ u, -1.0, 1.0)).tolist())
            h = np.array([v[1] for v in vals])
            heights.extend(np.abs(h - np.median(h)).tolist())
        if not tilts:
            return True, ""
        tilt, dz = float(np.median(tilts)), float(np.median(heights))
        if tilt <= opts.planar_max_tilt and dz <= opts.planar_max_height_change:
            return True, ""
        note = (f"the ring tilts by {np.degrees(tilt):.1f} deg and changes height by {dz:.3f} m between stations "
                f"(medians; a ground robot on a flat floor: below {opts.planar_max_tilt_deg:.1f} deg and "
                f"{opts.planar_max_height_change:.2f} m): stations initialised in SE(3) instead of the planar prior "
                f"(set planar: false for a handheld or flying rig)")
        if note.split(":")[0] != getattr(self, "_last_station_note", "").split(":")[0]:
            logger.warning("mapping: %s", note)
        self._last_station_note = note
        return False, note

    def _station_pose(self, est_pos_s, est_s, T_W_m, mids, planar: bool = True) -> np.ndarray:
        """Station pose from its mapped markers.

        ``planar`` (a ground robot): a planar motion of W (x, y, yaw), see :meth:`_planar_station_pose`.
        Otherwise SE(3): a weighted rigid fit of the marker centres (all markers, also those seen
        ambiguously: their positions are good) and the corners of the unambiguous ones (their
        orientation decides the rotation when few markers are in view), robust to a marker whose
        mapped position disagrees with the others.
        """
        if planar:
            return self._planar_station_pose(est_pos_s, est_s, T_W_m, mids)
        P, Q, w, owner = [], [], [], []
        for k, m in enumerate(mids):
            T_b, wt = est_pos_s[m]
            P.append(T_b[:3, 3])
            Q.append(T_W_m[m][:3, 3])
            w.append(wt)
            owner.append(k)
            # Corners: full weight for an unambiguous view, a token weight otherwise (they only
            # matter when nothing else fixes the rotation).
            T_c, wc = (est_s[m][0], wt) if m in est_s else (T_b, 1e-3 * wt)
            c = marker_corners(self.sizes(m))
            P.extend(geo.transform_points(T_c, c))
            Q.extend(geo.transform_points(T_W_m[m], c))
            w.extend([wc] * 4)
            owner.extend([k] * 4)
        P, Q, w, owner = np.array(P), np.array(Q), np.array(w), np.array(owner)
        centre = np.array([np.flatnonzero(owner == k)[0] for k in range(len(mids))])
        return _robust_fit(lambda keep: geo.rigid_fit(P[keep[owner]], Q[keep[owner]], w[keep[owner]]),
                           P[centre], Q[centre])

    @staticmethod
    def _planar_station_pose(est_pos_s, est_s, T_W_m, mids) -> np.ndarray:
        """Planar station pose (ground robot) from its mapped markers.

        The robot drives on the floor, so a station is a planar motion of W (x, y, yaw). With two
        or more markers it is fitted to the marker *centres* (weighted 2D Kabsch): single-marker
        orientations of small, far, face-on markers are uncertain by degrees, their positions by
        millimetres. With one marker its full pose is used (if unambiguous).
        """
        w = np.array([est_pos_s[m][1] for m in mids])
        P = np.array([est_pos_s[m][0][:3, 3] for m in mids])      # in the station's base frame
        Q = np.array([T_W_m[m][:3, 3] for m in mids])             # in W
        if not MapBuilder._two_apart([est_pos_s[m][0] for m in mids]):
            # One marker (or all on one vertical line): the bearing comes from marker orientations.
            full = [m for m in mids if m in est_s] or list(mids)
            src = est_s if all(m in est_s for m in full) else est_pos_s
            Ts = [T_W_m[m] @ geo.inverse(src[m][0]) for m in full]
            return geo.average_transforms(Ts, [src[m][1] for m in full]) if len(Ts) > 1 else Ts[0]
        return _robust_fit(lambda keep: MapBuilder._planar_fit(P[keep], Q[keep], w[keep]), P, Q)

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

    def _misread(self, groups: List[_Group]) -> Dict[int, str]:
        """Markers that look like misread ids: at every station with enough frames where they were
        seen, each camera that saw them did so in fewer than ``min_detection_ratio`` of its frames
        there (a real marker in view is detected in nearly every frame of a still robot; a misread
        one flickers: the driven simulated run had ids 445 and 662, not in the scene, 1-3 times in
        660 frames)."""
        ratio = self.options.min_detection_ratio
        if ratio <= 0:
            return {}
        best: Dict[int, Tuple[float, int, int]] = {}   # marker -> (best ratio, detections, frames)
        for g in groups:
            n = self._camera_frames.get((g.station, g.camera), 0)
            if n >= RATIO_MIN_FRAMES:
                best[g.marker_id] = max(best.get(g.marker_id, (0.0, 0, 0)), (len(g.members) / n, len(g.members), n))
        out = {}
        for m, (r, k, n) in best.items():
            if r < ratio:
                out[m] = (f"detected in only {k} of {n} frames of a camera that had it in view (mapping/"
                          f"min_detection_ratio {ratio}): a misread id, not a marker")
        return out

    def _check_spread(self, est_pos, T_W_s, ref: int, ref_st: int, T_W_m, planar: bool = True) -> Dict[int, str]:
        """Markers whose positions from different stations disagree by more than ``max_marker_spread``.

        Only stations whose pose does not rest on the marker under test, nor on one marker's
        orientation, testify: the reference station, and stations that see at least two *other*
        mapped markers apart (their pose is fitted to marker centres, :meth:`_station_pose`). A
        station linked through one far marker has the yaw error of that marker's single-view
        orientation (2-3 deg at 5 m), which puts every other marker it sees 0.2-0.3 m off: that
        is the station's error, not the marker's, and it rejected good markers of a driven
        mapping run (issue 15). The adjustment (``refined``) fixes such stations. A station of a rig
        that does not stay flat (SE(3), not ``planar``) turns freely about the line through two
        markers: it testifies only with three other markers spanning a plane (:meth:`_spans_plane`;
        on TagSLAM's test_12 two-marker SE(3) stations put tag 88 0.3 m apart and it was refused, a
        tag that the adjustment fits and that took the map from 107 to 45 mm RMS against TagSLAM's).

        The spread is robust to a few badly placed stations (a moving rig has hundreds): with
        five or more stations, twice the 80th percentile of the distances to the median position;
        with fewer, the largest distance between two of them.
        """
        out: Dict[int, str] = {}
        pos: Dict[int, List[np.ndarray]] = defaultdict(list)
        for s, T_ws in T_W_s.items():
            seen = est_pos.get(s, {})
            for m, (T, _) in seen.items():
                others = [seen[k][0] for k in seen if k != m and k in T_W_m]
                if s != ref_st and not (self._two_apart(others) if planar else self._spans_plane(others)):
                    continue
                pos[m].append((T_ws @ T)[:3, 3])
        for m, ps in pos.items():
            if len(ps) < 2 or m == ref:
                continue
            P = np.array(ps)
            if len(P) >= 5:
                spread = 2.0 * float(np.percentile(np.linalg.norm(P - np.median(P, axis=0), axis=1), 80))
            else:
                spread = float(np.max(np.linalg.norm(P[:, None] - P[None], axis=-1)))
            if not spread <= self.options.max_marker_spread:
                out[m] = (f"inconsistent between stations ({1000 * spread:.0f} mm apart): wrong size "
                          f"{self.sizes(m)} m (fiducial_len_override?), moved, or the id is printed twice")
        return out

    @staticmethod
    def _two_apart(T_base_markers: List[np.ndarray], min_apart: float = 0.05) -> bool:
        """True when at least two of these markers lie ``min_apart`` m apart horizontally (a
        station pose fitted to their centres, :meth:`_station_pose`)."""
        if len(T_base_markers) < 2:
            return False
        P = np.array([T[:2, 3] for T in T_base_markers])
        return float(np.linalg.norm(np.ptp(P, axis=0))) >= min_apart

    @staticmethod
    def _spans_plane(T_base_markers: List[np.ndarray], min_apart: float = 0.05) -> bool:
        """True when at least three of these markers' centres span a plane: the second largest
        singular value of their centred positions is at least ``min_apart`` m (an SE(3) station
        pose fitted to them cannot turn about a line)."""
        if len(T_base_markers) < 3:
            return False
        P = np.array([T[:3, 3] for T in T_base_markers])
        return float(np.linalg.svd(P - P.mean(axis=0), compute_uv=False)[1]) >= min_apart

    #: at most this many views (the most decisive ones) enter a consensus: it compares all pairs.
    _CONSENSUS_VIEWS = 48

    def _resolve_by_consensus(self, groups: List[_Group], T_W_s: Dict[int, np.ndarray]) -> Optional[np.ndarray]:
        """The candidate orientation that distinct viewpoints agree on, averaged; None if none.

        None too when the best-supported candidate has a rival (a candidate it does not agree
        with) supported as well: views from nearly one viewpoint agree on both solutions.
        """
        opts = self.options
        if len({(g.station, g.camera) for g in groups}) < opts.min_views_for_consensus:
            return None
        groups = sorted(groups, key=lambda g: (g.ambiguity, -len(g.members)))[: self._CONSENSUS_VIEWS]
        cands = [(T_W_s[g.station] @ g.T_base_marker(k), (g.station, g.camera))
                 for g in groups for k in range(len(g.candidates))]

        def agrees(Ta, Tb) -> bool:
            dp, dr = geo.pose_distance(Ta, Tb)
            return dp <= opts.consensus_distance and dr <= opts.consensus_angle

        support = [len({v for Tb, v in cands if v != view and agrees(Ta, Tb)}) for Ta, view in cands]
        k = int(np.argmax(support)) if support else -1
        if k < 0 or support[k] + 1 < opts.min_views_for_consensus:
            return None
        best = cands[k][0]
        rival = max((n for (Ta, _), n in zip(cands, support) if not agrees(best, Ta)), default=0)
        if rival >= support[k]:
            return None
        members = [Tb for Tb, _ in cands if agrees(best, Tb)]
        return geo.average_transforms(members)

    def _better_solution(self, groups: List[_Group], T_W_s: Dict[int, np.ndarray]) -> Tuple[np.ndarray, Tuple[float, float]]:
        """A marker the views do not resolve: its better IPPE solution from its most decisive view,
        and how far the other solution is from it (rad, m: the uncertainty it keeps)."""
        g = min(groups, key=lambda g: (g.ambiguity, -len(g.members)))
        T = T_W_s[g.station] @ g.T_base_marker(0)
        if len(g.candidates) > 1:
            dp, dr = geo.pose_distance(g.candidates[0], g.candidates[1])
        else:
            dp, dr = 0.0, 0.0
        return T, (float(dr), float(dp))

    # --- output -----------------------------------------------------------------------------

    def unlinked_markers(self) -> List[int]:
        """Markers seen but never linked to the mapped set (no common instant with it)."""
        return list(self._initialize().unlinked)

    def rejected_markers(self) -> Dict[int, str]:
        """Markers seen and linked but not mapped, with the reason."""
        return dict(self._initialize().rejected)

    @property
    def last_station(self) -> Optional[int]:
        """The station of the latest frame with detections (None before any)."""
        return self._last_station

    def station_pose(self, station: int, marker_map: MarkerMap) -> Optional[np.ndarray]:
        """Planar ``T_map_base`` of the robot at ``station`` in ``marker_map``'s frame, or None when it
        saw none of the map's markers: its own view of them fitted to where the map has them
        (:meth:`_station_pose`), so it holds for a paper and a refined map alike."""
        self._initialize()
        groups = [g for g in self._last_groups if g.station == station and g.marker_id in marker_map]
        if not groups:
            return None
        est_pos = self._station_marker_estimates(groups, lambda g: True)[station]
        est = self._station_marker_estimates(groups, self._unambiguous).get(station, {})
        T = self._station_pose(est_pos, est, {m: marker_map.T_map_marker(m) for m in est_pos}, list(est_pos))
        return geo.transform_from_se2(*geo.se2_from_transform(T))

    def unmapped(self, marker_map: MarkerMap) -> Dict[int, str]:
        """Every marker detected at least once that ``marker_map`` lacks, with the reason."""
        init = self._initialize()
        kept = {o.marker_id for o in self._obs}
        out: Dict[int, str] = {}
        for m in sorted(self.seen):
            if m in marker_map:
                continue
            if m in init.rejected:
                out[m] = init.rejected[m]
            elif m in init.unplaced:
                out[m] = init.unplaced[m]
            elif m in init.unlinked:
                out[m] = "never seen together with mapped markers: drive so that it is"
            elif m not in kept:
                out[m] = "every detection was dropped (see the warnings: reprojection, too far, no pose)"
            else:
                out[m] = "not linked to the reference marker's station"
        return out

    def format_unmapped(self, marker_map: MarkerMap, multiline: bool = False) -> str:
        """``""`` when every detected marker is in ``marker_map``, else a loud warning with the reasons
        (one sentence, or with ``multiline`` one indented line per marker)."""
        missing = self.unmapped(marker_map)
        if not missing:
            return ""
        sep = "\n  marker " if multiline else "; "
        return (f"WARNING: {len(missing)} of {len(self.seen)} detected markers are NOT in the map:"
                + ("\n  marker " if multiline else " ") + sep.join(f"{m}: {why}" for m, why in missing.items()))

    @property
    def reference(self) -> Optional[int]:
        """The reference marker that the current data gives (None before any usable detection)."""
        return self._initialize().reference

    def summary(self) -> Dict[str, Any]:
        """Progress: frames, stations, mapped markers, observations per marker, unlinked, rejected,
        ambiguous (mapped with the better of two solutions), the station model in use."""
        init = self._initialize()
        per_marker = defaultdict(int)
        for o in self._obs:
            per_marker[o.marker_id] += 1
        # Markers the last refined build rejected after its adjustment (same observations).
        after_ba = self._refine_rejected[1] if self._refine_rejected[0] == self._version else {}
        mapped = sorted(m for m in init.T_W_markers if m not in after_ba)
        return {
            "frames": self.frames,
            "stations": self.station_count,
            "linked_stations": len(init.T_W_stations),
            "skipped_moving_frames": self.skipped_moving,
            "reference_marker": init.reference,
            "mapped": mapped,
            "observations": {m: per_marker[m] for m in sorted(per_marker)},
            "unlinked": list(init.unlinked),
            "rejected": {**init.rejected, **after_ba},
            "ambiguous": sorted(m for m in init.ambiguous if m not in after_ba),
            "station_model": "planar" if init.planar else "se3",
            "station_note": init.station_note,
            "anchor_seeded_groups": len(init.seeds),
            "rejected_detections": dict(self.rejected_detections),
            "surveyed_only": self.surveyed_unseen()[0],
            "surveyed_not_mapped": self.surveyed_unseen()[1],
        }

    def format_summary(self) -> str:
        s = self.summary()
        obs = ", ".join(f"{m}:{n}" for m, n in s["observations"].items() if m in s["mapped"])
        text = (f"{len(s['mapped'])} markers mapped from {s['frames']} frames, {s['linked_stations']}/{s['stations']} "
                f"stations ({s['station_model']}), chained from marker {s['reference_marker']}; observations per marker "
                f"{{{obs}}}")
        if s["ambiguous"]:
            text += (f"; orientation ambiguous (one viewpoint, better solution kept, large uncertainty): "
                     f"{s['ambiguous']}")
        if s.get("anchor_seeded_groups"):
            text += (f"; {s['anchor_seeded_groups']} group(s) never seen with the others placed through their "
                     f"surveyed markers")
        if s["surveyed_only"]:
            text += (f"; {len(s['surveyed_only'])} surveyed marker(s) never detected, mapped from the survey alone "
                     f"(surveyed_only): {s['surveyed_only']}")
        if s["surveyed_not_mapped"]:
            text += f"; surveyed but never detected, NOT mapped: {s['surveyed_not_mapped']}"
        if s["unlinked"]:
            text += f"; seen but not linked: {s['unlinked']}"
        if s["rejected"]:
            text += f"; rejected: {sorted(s['rejected'])}"
        return text

    def _frame(self, T_W_ref: np.ndarray, ref: int) -> Tuple[np.ndarray, str]:
        """``T_W_map`` and the frame's definition for the reference marker's pose ``T_W_ref``."""
        if self.options.frame == "marker":
            return np.array(T_W_ref, dtype=float), f"marker {ref}'s own frame (fiducial_slam's convention)"
        try:
            T = map_frame_from_reference(T_W_ref)
        except GeometryError as exc:
            raise ArucoRingError(f"map frame 'floor': {exc} (in the ring's base frame '{self.ring.base_frame}'; "
                                 f"use frame: marker, or another reference_marker)") from None
        return T, (f"origin on the floor below marker {ref}'s centre, z up (the z of base frame "
                   f"'{self.ring.base_frame}' at the reference station), x along marker {ref}'s x made horizontal")

    def build(self, method: Optional[str] = None) -> MarkerMap:
        """The map (``paper`` or ``refined``; default the builder's method).

        The map frame is ``options.frame`` (``floor`` or ``marker``). The map records its quality
        (reprojection RMS overall and per marker, stations, station model) and, for markers whose
        orientation no second viewpoint resolved, ``ambiguous`` with a rotation (and position)
        uncertainty that covers the other IPPE solution.

        Raises:
            ArucoRingError: no usable detection yet (or the reference marker was never seen), or
                the reference marker cannot fix a ``floor`` frame.
        """
        method = method or self.method
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        init = self._initialize()
        if init.reference is None:
            if self.reference_marker is not None:
                raise ArucoRingError(f"reference marker {self.reference_marker} was never seen unambiguously")
            raise ArucoRingError("no usable marker detection yet: nothing to map")
        if method == "paper":
            res, mids = None, sorted(init.T_W_markers)
            ref = init.reference
            T_W = {m: init.T_W_markers[m] for m in mids}
            per_obs = observation_rms_px(self._problem(init, mids))
        else:
            res, mids, init = self._refine(init)
            ref = self._refined_reference(init, res, mids)
            T_W = {m: res.T_W_markers[k] for k, m in enumerate(mids)}
            per_obs = res.per_obs_rms_px
        if self.anchors is not None:
            # Surveyed frame: a refined map is already in it (the adjustment ran there); a paper
            # map is the initialisation fitted to the anchors.
            anchors = self._surveyed(mids)
            fit = fit_frame(anchors, T_W)
            T_map_W = np.eye(4) if res is not None else fit.T_map_W
            T_W_map, ref, convention = geo.inverse(T_map_W), None, "survey"
            definition = frame_definition(anchors, fit.kind)
        else:
            # The map frame is fixed to the (refined) reference marker; W is the ring's base frame at
            # the reference station (the gauge of the adjustment).
            T_W_map, definition = self._frame(T_W[ref], ref)
            T_map_W = geo.inverse(T_W_map)
            convention = self.options.frame
        out = MarkerMap(frame_id=self.frame_id, reference_marker=ref, frame_definition=definition, method=method,
                        frame_convention=convention)
        obs_k = np.array([k for k, m in enumerate(mids) for _ in init.marker_obs.get(m, [])], dtype=int)
        n_k = np.bincount(obs_k, minlength=len(mids))
        ss_k = np.bincount(obs_k, weights=np.square(per_obs), minlength=len(mids))
        rms = {m: float(np.sqrt(ss_k[k] / n_k[k])) for k, m in enumerate(mids) if n_k[k]}
        for k, m in enumerate(mids):
            if res is None:
                pstd, rstd = self._paper_std(m, init, T_W_map)
            elif res.marker_cov is not None:
                pstd, rstd = marker_std_in_frame(res.marker_cov[k], T_W[m], T_W_map)
            else:
                pstd, rstd = np.zeros(3), np.zeros(3)
            amb = m in init.ambiguous
            if amb:
                angle, dist = init.ambiguous[m]
                rstd = np.maximum(rstd, angle)
                pstd = np.maximum(pstd, dist)
            out.add(MarkerEntry(m, T_map_W @ T_W[m], self.sizes(m), pstd, rstd, len(init.marker_obs.get(m, [])),
                                ambiguous=amb, rms_px=rms.get(m)))
        out.quality = {"reprojection_rms_px": float(np.sqrt(np.mean(np.square(per_obs)))) if len(per_obs) else 0.0,
                       "frames": int(self.frames), "stations": len(init.T_W_stations),
                       "station_model": "planar" if init.planar else "se3",
                       "pixel_noise": float(self.options.ba.pixel_noise)}
        if init.station_note and not init.planar:
            out.quality["station_note"] = init.station_note
        if self.anchors is not None:
            out.anchors = anchor_report(self.anchors, {e.marker_id: e.T_map_marker for e in out}, fit.kind)
            placed = self._add_surveyed_unseen(out)
            unseen = set(self.surveyed_unseen()[1])       # warned about by _add_surveyed_unseen
            for p in out.anchors["points"]:
                if p["marker"] in unseen:
                    continue
                if p["marker"] in placed:
                    # Its pose is the survey's: no residual to judge, said in the report.
                    del p["mapped"]
                    p["surveyed_only"] = True
                elif "residual" in p:
                    logger.info("mapping: anchor marker %d mapped %.1f mm (%.1f sigma) from its surveyed position",
                                p["marker"], 1000 * float(np.linalg.norm(p["residual"])), p["residual_sigmas"])
                else:
                    logger.warning("mapping: surveyed marker %d is not in the map (%s): the frame rests on the "
                                   "others", p["marker"], self.anchors.source)
        if self.measurements is not None:
            self._record_measurements(out)
        if res is not None and self._refines_extrinsics:
            # The markers were estimated through these extrinsics: localizing with them removes the
            # ring's calibration error from every pose (ring_tf publishes them given the map file).
            out.ring_extrinsics = {c: res.T_base_cams[k] for k, c in enumerate(self.ring.names)}
            out.ring_base_frame = self.ring.base_frame
            sigma = self._extrinsics_sigma(self.ring.names)
            # The sanity check's scale of how far a camera may move: with per-camera priors, the loosest.
            out.ring_prior_sigma = ({"translation": float(self.options.ba.extrinsics_trans_sigma),
                                     "rotation": float(self.options.ba.extrinsics_rot_sigma)} if sigma is None else
                                    {"translation": float(sigma[:, 3:].max()), "rotation": float(sigma[:, :3].max())})
            out.ring_moved = {c: geo.pose_distance(self.ring[c].T_base_cam, T) for c, T in out.ring_extrinsics.items()}
            if res.camera_cov is not None:  # their uncertainty, for the localizer's noise model
                out.ring_covariance_cameras = list(self.ring.names)
                out.ring_extrinsics_covariance = camera_cov_in_optical_frames(res.camera_cov, res.T_base_cams)
        return out

    def surveyed_unseen(self) -> Tuple[List[int], List[int]]:
        """The surveyed markers the recording never detected: (with a full pose: put in the map from
        the survey when ``options.surveyed_unseen``; position only: cannot be placed), by id."""
        if self.anchors is None:
            return [], []
        unseen = [a for a in self.anchors.anchors if a.marker_id not in self.seen]
        full = [a.marker_id for a in unseen if a.rotation is not None]
        return (full if self.options.surveyed_unseen else []), \
            [a.marker_id for a in unseen if a.rotation is None or not self.options.surveyed_unseen]

    def _add_surveyed_unseen(self, out: MarkerMap) -> List[int]:
        """Put the surveyed markers no detection saw (full poses) into ``out`` (whose frame is the
        surveyed frame) at their surveyed poses with the survey's std, flagged ``surveyed_only``;
        their ids. Position-only ones are logged as not mapped."""
        full, missing = self.surveyed_unseen()
        by_id = {a.marker_id: a for a in self.anchors.anchors} if self.anchors is not None else {}
        for m in full:
            a = by_id[m]
            out.add(MarkerEntry(m, geo.make_transform(a.rotation, a.position), self.sizes(m),
                                np.asarray(a.position_std, dtype=float).copy(), np.full(3, float(a.rotation_std)), 0,
                                surveyed_only=True))
        if full:
            logger.info("mapping: %d surveyed marker(s) never detected put in the map from the survey alone "
                        "(surveyed_only, %s): %s", len(full), self.anchors.source, full)
        if missing and self.anchors is not None:
            why = "surveyed_unseen is off" if not self.options.surveyed_unseen else "surveyed position only"
            logger.warning("mapping: surveyed marker(s) %s never detected and not mapped (%s, %s)", missing, why,
                           self.anchors.source)
        return full

    def save_map(self, path: str, method: Optional[str] = None, backups: int = 1) -> MarkerMap:
        """Build the map (:meth:`build`) and write it to ``path`` atomically (previous file kept as
        ``<path>.bak``, ``backups`` generations: :meth:`MarkerMap.save`): what the mapper's ``~save_map`` and
        ``save_on_shutdown`` do. A crash at any instant leaves the old file or the new one whole.
        The map must pass the sanity checks (``options.sanity``, :func:`marker_map.check_map`);
        when it does not, nothing is written.

        Raises:
            ArucoRingError: nothing to map yet; MapSanityError: a check failed (the message names
            it, the markers and what to do); ConfigError: the file cannot be written.
        """
        m = self.build(method)
        m.save(path, self.options.sanity, backups=backups)
        return m

    def _record_measurements(self, out: MarkerMap) -> None:
        """The survey measurements' residuals in the map (``quality.survey_measurements``,
        :func:`anchors.measurement_report`), logged."""
        assert self.measurements is not None
        rep = measurement_report(self.measurements, {e.marker_id: e.T_map_marker for e in out}, self.sizes)
        out.quality["survey_measurements"] = rep
        for e in rep["distances"] + rep["planes"]:
            if "residual_mm" in e:
                logger.info("mapping: survey %s off by %+.2f mm (%.1f sigma)", e["key"], e["residual_mm"],
                            e["residual_sigmas"])
            else:
                logger.warning("mapping: survey %s: its markers are not in the map (%s)", e["key"],
                               self.measurements.source)

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
        if (self.reference_marker is not None or not self.options.refined_reference or self.anchors is not None
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

    def _surveyed(self, mids: List[int]) -> AnchorSet:
        """The anchors among the mapped markers ``mids``; ArucoRingError while they cannot fix the
        frame yet (the live map waits for them, a save says which are missing)."""
        assert self.anchors is not None
        try:
            return self.anchors.subset(mids)
        except ConfigError:
            have = [m for m in self.anchors.ids if m in set(mids)]
            raise ArucoRingError(f"surveyed frame ({self.anchors.source}): {len(have)} of the surveyed markers "
                                 f"{self.anchors.ids} mapped ({have}); the frame needs 2 of them, or 1 with a "
                                 f"surveyed pose: map until the others are seen") from None

    def _problem(self, init: _Init, mids: List[int]) -> BAProblem:
        """The adjustment problem of the initialisation: every kept observation of ``mids``."""
        sts = sorted(init.T_W_stations)
        cams = self.ring.names
        mi = {m: k for k, m in enumerate(mids)}
        si = {s: k for k, s in enumerate(sts)}
        ci = {c: k for k, c in enumerate(cams)}
        idx = [i for m in mids for i in init.marker_obs.get(m, [])]
        obs = [self._obs[i] for i in idx]
        T_m = np.stack([init.T_W_markers[m] for m in mids])
        T_s = np.stack([init.T_W_stations[s] for s in sts])
        fixed_station: Optional[int] = si[init.ref_station]
        priors = None
        if self.anchors is not None:
            # The surveyed frame: the initialisation fitted to the anchors, which then replace the
            # fixed station as the gauge (priors weighted by their std).
            anchors = self._surveyed(mids)
            fit = fit_frame(anchors, init.T_W_markers)
            T_m = fit.T_map_W @ T_m
            T_s = fit.T_map_W @ T_s
            pos = anchors.anchors
            rot = [a for a in pos if a.rotation is not None]
            priors = MarkerPriors(position_marker=[mi[a.marker_id] for a in pos],
                                  position=[a.position for a in pos], position_std=[a.position_std for a in pos],
                                  rotation_marker=[mi[a.marker_id] for a in rot], rotation=[a.rotation for a in rot],
                                  rotation_std=[a.rotation_std for a in rot],
                                  level_station=([fixed_station] if fit.kind == "points_level" else [])
                                  + [si[s] for s, k in init.seeds.items() if k == "points_level"],
                                  level_sigma=LEVEL_SIGMA)
            fixed_station = None
        if self.measurements is not None:
            priors = self._measurement_priors(priors, mi)
        # Each observation carries the extrinsics in force when it was taken; the solver keeps one
        # per camera: the ring's current one.
        return BAProblem(
            T_W_markers=T_m,
            sizes=np.array([self.sizes(m) for m in mids]),
            T_W_stations=T_s,
            T_base_cams=np.stack([self.ring[c].T_base_cam for c in cams]),
            obs_marker=np.array([mi[o.marker_id] for o in obs], dtype=int),
            obs_station=np.array([si[o.station] for o in obs], dtype=int),
            obs_camera=np.array([ci[o.camera] for o in obs], dtype=int),
            obs_xy=np.stack([o.xy for o in obs]),
            obs_focal=np.stack([o.focal for o in obs]),
            obs_lens=np.stack([o.lens for o in obs]),
            fixed_marker=None,
            fixed_station=fixed_station,
            priors=priors,
            T_base_cams_start=np.stack([init.extrinsics.get(c, self.ring[c].T_base_cam) for c in cams]),
            odometry=self._odometry_factors(sts, si),
            extrinsics_sigma=self._extrinsics_sigma(cams),
        )

    def _measurement_priors(self, priors: Optional[MarkerPriors], mi: Dict[int, int]) -> Optional[MarkerPriors]:
        """``priors`` with the survey measurements among the mapped markers (``mi``: id -> index)
        added: distances between marker points, points on planes (in the surveyed frame, where the
        adjustment runs with anchors); measurements of markers not mapped are left out."""
        assert self.measurements is not None
        dist = [d for d in self.measurements.distances if d.a.marker_id in mi and d.b.marker_id in mi]
        pts = [(p, pl) for pl in self.measurements.planes for p in pl.marker_points() if p.marker_id in mi]
        if not dist and not pts:
            return priors
        out = priors if priors is not None else MarkerPriors()
        return dataclasses.replace(
            out,
            distance_marker=[[mi[d.a.marker_id], mi[d.b.marker_id]] for d in dist],
            distance_point=np.array([[d.a.local(self.sizes(d.a.marker_id)), d.b.local(self.sizes(d.b.marker_id))]
                                     for d in dist]).reshape(-1, 2, 3),
            distance=[d.distance for d in dist], distance_std=[d.std for d in dist],
            plane_marker=[mi[p.marker_id] for p, _ in pts],
            plane_point=np.array([p.local(self.sizes(p.marker_id)) for p, _ in pts]).reshape(-1, 3),
            plane_normal=np.array([pl.normal for _, pl in pts]).reshape(-1, 3),
            plane_offset=[pl.distance for _, pl in pts], plane_std=[pl.std for _, pl in pts])

    def _refine(self, init: _Init) -> Tuple[BAResult, List[int], _Init]:
        """The bundle adjustment, and again without the markers that do not fit it.

        A marker whose observations still reproject worse than ``max_marker_rms_px`` (or
        ``max_marker_rms_sigmas`` ``ba.pixel_noise``: :attr:`MappingOptions.marker_rms_limit_px`) after the
        adjustment (a flipped initial pose the adjustment could not leave, tiny tags at grazing
        angles, a wrong size) is rejected with the reason and the adjustment redone without it
        (twice at most): a map of the markers that fit rather than a map that fails its checks.
        Returns (result, marker ids, the initialisation without the rejected markers).
        """
        opts = self.options.ba
        if opts.refine_extrinsics and not self._refines_extrinsics:
            opts = dataclasses.replace(opts, refine_extrinsics=False)
        rejected: Dict[int, str] = {}
        boards = self._active_boards()
        if boards is not None:
            init = self._place_boards(init, boards)
        n_rejections = 0
        limit = self.options.marker_rms_limit_px
        # Rejections at most twice; with boards, dropping the views that do not fit their board does
        # not count (at most twice as well).
        for attempt in range(3 if boards is None else 5):
            mids = sorted(init.T_W_markers)
            res = self._adjust(self._problem(init, mids), mids, opts, boards)
            obs_k = np.array([k for k, m in enumerate(mids) for _ in init.marker_obs.get(m, [])], dtype=int)
            n_k = np.maximum(np.bincount(obs_k, minlength=len(mids)), 1)
            rms = np.sqrt(np.bincount(obs_k, weights=np.square(res.per_obs_rms_px), minlength=len(mids)) / n_k)
            # A surveyed marker stays (the sanity checks name it if it does not fit): without it a group
            # placed through it would have nothing to hold it.
            surveyed = set(self.anchors.ids) if self.anchors is not None else set()
            bad = [m for k, m in enumerate(mids) if rms[k] > limit and m != init.reference
                   and m not in surveyed]
            if not bad or n_rejections == 2 or attempt == (2 if boards is None else 4) or len(bad) >= len(mids) - 1:
                break
            if boards is not None:
                # A board's marker whose views do not fit stays where its board puts it (its views
                # dropped, as TagSLAM drops grazing ones) while other markers of the board are seen.
                held = self._held_by_board(bad, init, boards)
                if held:
                    logger.warning("mapping: the views of markers %s do not fit their boards (over %g px RMS): "
                                   "dropped, the markers placed by their boards' layout", held,
                                   limit)
                    init = dataclasses.replace(init, marker_obs={m: ([] if m in held else v)
                                                                 for m, v in init.marker_obs.items()})
                    bad = [m for m in bad if m not in held]
                    if not bad:
                        continue
            n_rejections += 1
            for m in bad:
                rejected[m] = (f"reprojects at {rms[mids.index(m)]:.1f} px RMS after the adjustment (limit "
                               f"{limit:g} px): a flipped pose, a tag too small or seen "
                               f"too obliquely, or a wrong size")
                logger.warning("mapping: marker %d rejected: %s", m, rejected[m])
            keep = {m: T for m, T in init.T_W_markers.items() if m not in rejected}
            init = dataclasses.replace(init, T_W_markers=keep,
                                       marker_obs={m: v for m, v in init.marker_obs.items() if m in keep},
                                       ambiguous={m: v for m, v in init.ambiguous.items() if m in keep},
                                       rejected={**init.rejected, **rejected})
        if opts.refine_extrinsics:
            self._remove_common_extrinsics_motion(res)
        self.last_ba = res
        self._refine_rejected = (self._version, dict(rejected))
        return res, mids, init

    def _active_boards(self) -> Optional[BoardSet]:
        """The boards the adjustment merges: all but those holding a surveyed marker (an anchor is a
        prior on its own marker's pose, which a board's unknown does not have); None without any."""
        if self.boards is None or not len(self.boards):
            return None
        if self.anchors is None:
            return self.boards
        surveyed = set(self.anchors.ids)
        skip = [b.name for b in self.boards.boards if surveyed & set(b.layout)]
        if skip:
            logger.info("mapping: boards %s hold surveyed markers: their markers are mapped one by one", skip)
        out = self.boards.without(skip)
        return out if len(out) else None

    def _place_boards(self, init: _Init, boards: BoardSet) -> _Init:
        """Every marker of a board with a mapped, observed marker, placed by the board's layout.

        The board's pose is fitted to its mapped markers (:func:`boards.fit_board_pose`: a mirrored
        or ambiguous single-marker pose is outvoted); its markers the initialisation rejected or
        never reached get their views at the initialised stations back (the adjustment weighs them
        through the board), and its markers never detected are placed from the layout alone.
        """
        T_W = dict(init.T_W_markers)
        obs = {m: list(v) for m, v in init.marker_obs.items()}
        amb = dict(init.ambiguous)
        rejected = dict(init.rejected)
        stations = set(init.T_W_stations)
        views: Dict[int, List[int]] = {}
        for i, o in enumerate(self._obs):
            if o.station in stations and boards.board_of(o.marker_id) is not None:
                views.setdefault(o.marker_id, []).append(i)
        for board in boards.boards:
            have = [m for m in board.ids if m in T_W and obs.get(m)]
            if not have:
                continue
            weights = {m: len(obs[m]) * (0.01 if m in amb else 1.0) for m in have}
            T_b, agree = fit_board_pose(board, {m: T_W[m] for m in have}, weights)
            added = [m for m in board.ids if m not in T_W]
            for m in board.ids:
                T_W[m] = T_b @ board.layout[m]
                if not obs.get(m):
                    obs[m] = list(views.get(m, []))
                rejected.pop(m, None)
                if len(agree) >= 2:
                    amb.pop(m, None)
            if added:
                logger.info("mapping: board %s (%d of its markers mapped, %d agreeing) places markers %s",
                            board.name, len(have), len(agree), added)
        return dataclasses.replace(init, T_W_markers=T_W, marker_obs=obs, ambiguous=amb, rejected=rejected,
                                   unlinked=[m for m in init.unlinked if m not in T_W],
                                   unplaced={m: v for m, v in init.unplaced.items() if m not in T_W})

    @staticmethod
    def _held_by_board(bad: List[int], init: _Init, boards: BoardSet) -> List[int]:
        """The markers of ``bad`` whose board keeps other observed markers that are not bad."""
        out = []
        for m in bad:
            b = boards.board_of(m)
            if b is None:
                continue
            others = [n for n in boards.boards[b].layout if n != m and n not in bad and init.marker_obs.get(n)]
            if others:
                out.append(m)
        return out

    @staticmethod
    def _adjust(prob: BAProblem, mids: List[int], opts, boards: Optional[BoardSet]) -> BAResult:
        """:func:`bundle_adjust` of ``prob`` (markers ``mids``), each board one unknown when there
        are boards (:func:`boards.collapse`), the result given back per marker."""
        if boards is None:
            return bundle_adjust(prob, opts)
        if any(b.loose for b in boards.boards):
            # Loose boards: their markers stay unknowns of their own, tied to a board frame each.
            prob = MapBuilder._with_loose_boards(prob, mids, boards.loose())
            boards = boards.rigid()
            if not len(boards):
                res = bundle_adjust(prob, opts)
                return MapBuilder._drop_board_frames(res, len(mids))
            n_frames = len(prob.T_W_markers) - len(mids)
            mids = list(mids) + [-1 - j for j in range(n_frames)]    # ids on no board: one unit each
            return MapBuilder._drop_board_frames(MapBuilder._adjust(prob, mids, opts, boards), len(mids) - n_frames)
        T_u, sizes_u, X, c = collapse(mids, prob.T_W_markers, prob.sizes, prob.obs_marker, boards)
        priors = prob.priors
        if priors is not None:
            priors = dataclasses.replace(priors, position_marker=c.unit[priors.position_marker],
                                         rotation_marker=c.unit[priors.rotation_marker])
            if len(priors.distance_marker) or len(priors.plane_marker):
                # Measured points of a board's marker: in the board's frame (its layout).
                def in_unit(k: np.ndarray, X: np.ndarray) -> np.ndarray:
                    T = c.T_unit_marker[k]
                    return (T[:, :3, :3] @ X[..., None])[..., 0] + T[:, :3, 3]

                dm = priors.distance_marker
                priors = dataclasses.replace(
                    priors, distance_marker=c.unit[dm],
                    distance_point=np.stack([in_unit(dm[:, 0], priors.distance_point[:, 0]),
                                             in_unit(dm[:, 1], priors.distance_point[:, 1])], axis=1)
                    if len(dm) else priors.distance_point,
                    plane_marker=c.unit[priors.plane_marker],
                    plane_point=in_unit(priors.plane_marker, priors.plane_point) if len(priors.plane_marker)
                    else priors.plane_point)
            if len(priors.relative_marker):
                # Loose boards' frames and markers are on no rigid board: their own units.
                priors = dataclasses.replace(priors, relative_marker=c.unit[priors.relative_marker])
        sub = dataclasses.replace(prob, T_W_markers=T_u, sizes=sizes_u, obs_marker=c.unit[prob.obs_marker],
                                  obs_object=X, priors=priors)
        res = bundle_adjust(sub, opts)
        cov = expand_covariances(res.marker_cov, res.T_W_markers, c) if res.marker_cov is not None else None
        return dataclasses.replace(res, T_W_markers=expand_poses(res.T_W_markers, c), marker_cov=cov)

    @staticmethod
    def _with_loose_boards(prob: BAProblem, mids: List[int], loose: BoardSet) -> BAProblem:
        """``prob`` with a frame per loose board appended to its markers (no observations; its
        size a placeholder) and each of the board's markers tied to it by its layout's prior
        (:func:`boards.loose_priors`)."""
        frames, pairs, poses, pos_std, rot_std, _ = loose_priors(mids, prob.T_W_markers, loose)
        if not len(frames):
            return prob
        priors = prob.priors if prob.priors is not None else MarkerPriors()
        priors = dataclasses.replace(
            priors, relative_marker=np.concatenate([priors.relative_marker, pairs]),
            relative_pose=np.concatenate([priors.relative_pose, poses]),
            relative_position_std=np.concatenate([priors.relative_position_std, pos_std]),
            relative_rotation_std=np.concatenate([priors.relative_rotation_std, rot_std]))
        return dataclasses.replace(prob, T_W_markers=np.concatenate([prob.T_W_markers, frames]),
                                   sizes=np.concatenate([prob.sizes, np.ones(len(frames))]), priors=priors)

    @staticmethod
    def _drop_board_frames(res: BAResult, n_markers: int) -> BAResult:
        """``res`` without the loose boards' frames (the unknowns after the first ``n_markers``)."""
        cov = res.marker_cov[:n_markers] if res.marker_cov is not None else None
        return dataclasses.replace(res, T_W_markers=res.T_W_markers[:n_markers], marker_cov=cov)

    @property
    def _refines_extrinsics(self) -> bool:
        """``ba.refine_extrinsics``, for a ring of two cameras or more: only the cameras' poses
        relative to each other are observable, a single camera's extrinsics are not at all."""
        return bool(self.options.ba.refine_extrinsics) and len(self.ring) > 1

    def _extrinsics_sigma(self, cams: Sequence[str]) -> Optional[np.ndarray]:
        """(C, 6) prior std of the extrinsics of ``cams`` (rotation rad, translation m, per axis of the
        base frame, :attr:`BAProblem.extrinsics_sigma`) with ``extrinsics_prior: ring``: each camera's
        ``extrinsics_std`` (per axis of its optical frame) turned into the base frame (the diagonal of
        ``R diag(std^2) R^T``: exact for the same std on the three axes, the correlations dropped
        otherwise), at least :data:`MIN_EXTRINSICS_SIGMA`; None with ``options`` (the BA options' for all)."""
        if self.options.extrinsics_prior != "ring":
            return None
        out = np.zeros((len(cams), 6))
        for k, name in enumerate(cams):
            cam = self.ring[name]
            R = cam.T_base_cam[:3, :3]
            std = np.asarray(cam.extrinsics_std, dtype=float)
            for a in (0, 3):
                out[k, a:a + 3] = np.sqrt(np.einsum("ij,j,ij->i", R, std[a:a + 3] ** 2, R))
        return np.maximum(out, MIN_EXTRINSICS_SIGMA)

    def _remove_common_extrinsics_motion(self, res: BAResult) -> None:
        """Take out of the refined extrinsics the motion common to all cameras (in place).

        Moving every camera by the same ``D`` in the base frame while the world moves by ``D`` too
        (markers ``D T_W_m``, stations ``D T_W_s D^-1``; the reference station stays the identity)
        changes no projection: only the extrinsics *relative to each other* are observable, the
        common part is the priors' pull alone, where the solver stops short (a single camera
        "moved" 5 mm, pure gauge, and the localizer then shifted every pose by it). Choosing ``D``
        so that the cameras' mean motion from the calibration is zero keeps the base frame the
        calibration's; the map relative to its reference marker is unchanged.

        In a surveyed frame (anchors) the markers stay where the adjustment put them against the
        survey: the same projections come from cameras ``D T_base_cam`` and stations ``T_W_s D^-1``.
        """
        calib = [self.ring[c].T_base_cam for c in self.ring.names]
        motions = [res.T_base_cams[k] @ geo.inverse(E) for k, E in enumerate(calib)]
        sigma = self._extrinsics_sigma(self.ring.names)
        if sigma is None:
            D = geo.inverse(geo.average_transforms(motions))
        else:
            # Cameras held by unequal priors (extrinsics_prior: ring): the mean weighted by each
            # camera's prior information, so that a camera held at its calibration stays there.
            wr = 1.0 / np.mean(sigma[:, :3] ** 2, axis=1)
            wt = 1.0 / np.mean(sigma[:, 3:] ** 2, axis=1)
            M = np.eye(4)
            M[:3, :3] = Rotation.from_matrix(np.stack([T[:3, :3] for T in motions])).mean(weights=wr).as_matrix()
            M[:3, 3] = np.average(np.stack([T[:3, 3] for T in motions]), axis=0, weights=wt)
            D = geo.inverse(M)
        D_inv = geo.inverse(D)
        res.T_base_cams[:] = D @ res.T_base_cams
        if self.anchors is not None:
            res.T_W_stations[:] = res.T_W_stations @ D_inv
            return
        res.T_W_markers[:] = D @ res.T_W_markers
        res.T_W_stations[:] = D @ res.T_W_stations @ D_inv
        if res.marker_cov is not None:
            # Covariances (w, t) in W: rotated with W (D's translation does not change them).
            R = np.zeros((6, 6))
            R[:3, :3] = R[3:, 3:] = D[:3, :3]
            res.marker_cov[:] = R @ res.marker_cov @ R.T
