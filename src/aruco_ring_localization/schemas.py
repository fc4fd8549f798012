"""Every node's parameter schema: one nested frozen dataclass per node (:mod:`config` mechanism).

A node reads its private namespace once into its schema (``ros/params.read_config``); the command
line tools read the same schema from the same YAML file (``config/<node>.yaml``), so
``aruco_ring localize`` runs what the localizer node runs. Sections are the core's own parameter
dataclasses (:class:`localization.LocalizationParams`, :class:`gating.GateParams`,
:class:`kalman.FilterParams`, :class:`mapping.MappingOptions`, :class:`bundle_adjustment.BAOptions`,
:class:`detection.DetectorParams` ...), so each default is written once, where it is used.

==========================  =====================  ===========================
node                        schema                 YAML file
==========================  =====================  ===========================
localizer                   :class:`LocalizerConfig`   config/localization.yaml
mapper                      :class:`MapperConfig`      config/mapping.yaml
detector                    :class:`DetectorConfig`    config/detector.yaml
ring_tf                     :class:`RingTfConfig`      (launch arguments only)
comparison                  :class:`ComparisonConfig`  config/comparison.yaml
==========================  =====================  ===========================

The simulator's schema lives with the simulator node (``ros/simulator.py``).
``docs/parameters.md`` is generated from these classes (``tools/parameters_doc.py``), and a unit
test checks that the YAML files, the launch files, the docs and the classes agree.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from .evaluation import comparison as _comparison
from .config import default, param, require_positive, section
from .detection import DetectorParams
from .detections import parse_slop
from .errors import ConfigError
from .gating import GateParams
from .kalman import FilterParams
from .localization import LocalizationParams
from .odometry import MotionParams
from .mapping import METHODS, MappingOptions
from .marker_check import MarkerCheckParams
from .markers import MarkerSizes, parse_id_list
from .tracker6 import Tracker6Params

TF_MODES = ("auto", "map_to_odom", "map_to_base")
IMAGE_TRANSPORTS = ("raw", "compressed")


# --- shared by the mapper and the localizer ------------------------------------------------------

@dataclass(frozen=True)
class RingInputParams:
    """The ring's input: which cameras, where their calibration comes from, how frames are grouped."""

    cameras: Tuple[str, ...] = param([], "ring camera names (cam0) or namespaces (ring/cam0) to use; empty: all "
                                         "of the ring")
    use_tf: bool = param(True, "extrinsics base_link -> camK_optical_frame from tf (ring_tf publishes them); false: "
                               "the ring file's (for the localizer: those refined with the map when it has them)")
    camera_info_fallback: bool = param(False, "use the ring file's intrinsics while a camera has sent no "
                                              "camera_info (false: its detections are skipped, as aruco_detect)")
    slop: str = param("auto", "auto: a ring frame is one frame period of the cameras' stamps, the period and "
                              "the boundary between frames measured from the stamps (synchronized and "
                              "free-running cameras alike, docs/localization.md); or a number: detections whose "
                              "stamps differ by at most this form one ring frame", unit="s")
    timeout: float = param(0.25, "an incomplete ring frame goes out this long after its first camera (node's clock: "
                                 "ROS time); a silent camera never stalls the others", unit="s")
    silent_after: float = param(1.0, "a camera with no usable detections for this long is silent: ring frames stop "
                                     "waiting for it and the diagnostics report it", unit="s")
    ignore_fiducials: str = param("", "marker ids never used, aruco_detect syntax \"1,4,9-12\"")
    max_stamp_ahead: float = param(0.25, "a message stamped more than this after the node's clock (ROS time) is "
                                         "dropped with a throttled warning naming the topic and the offset: a "
                                         "future stamp is never used to predict, published or put on tf; covers "
                                         "clock skew between machines and one frame of /clock delivery in "
                                         "simulated time", unit="s")
    max_detections: int = param(200, "a camera message with more detections than this is dropped whole (a "
                                     "flood; no real image shows that many markers): the work per message and "
                                     "per ring frame stays bounded")
    camera_info_check_period: float = param(2.0, "nodes only: after a camera_info equal to the one in force, "
                                                 "that connection is read again only this long after (wall "
                                                 "time): the camera_info sent meanwhile wait in the socket and "
                                                 "only the newest is read, so a changed camera_info is applied "
                                                 "within this delay; 0: every camera_info is read as it comes; at "
                                                 "most 10",
                                            unit="s")

    def __post_init__(self) -> None:
        try:
            parse_slop(self.slop)
        except ValueError:
            raise ConfigError(f"expected auto or a number of seconds >= 0, got {self.slop!r}", key="slop") from None
        require_positive(self, "timeout", "silent_after", "max_stamp_ahead", "max_detections")
        if not 0.0 <= self.camera_info_check_period <= 10.0:
            # 10 s of 30 Hz camera_info is about 120 kB: what the socket buffers hold without the
            # publisher blocking (rospy without queue_size) or dropping (roscpp).
            raise ConfigError(f"must be in [0, 10] s, got {self.camera_info_check_period!r}",
                              key="camera_info_check_period")
        parse_id_list(self.ignore_fiducials, key="ignore_fiducials")

    def ignored_ids(self) -> frozenset:
        """The ids of ``ignore_fiducials``."""
        return frozenset(parse_id_list(self.ignore_fiducials, key="ignore_fiducials"))


# --- localizer -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class TimingParams:
    """Which ring frames and motion inputs are too old to use (the pipeline's time policy)."""

    max_frame_age: float = param(2.0, "a ring frame older than this (node's clock minus its stamp) when it is "
                                      "complete is dropped and counted, as is every ring frame that a newer one "
                                      "overtook: the estimator never falls behind; 0 disables the age test",
                                 unit="s")
    motion_timeout: float = param(0.5, "a cmd_vel or odom twist received (node's clock) longer ago than this "
                                       "counts as zero for the gate; a twist stamped older than this is stale too",
                                  unit="s")
    max_pause: float = param(1.0, "the node's clock moving more than this between two events (the process was "
                                  "stopped or starved, the machine suspended, a recording has a gap): the track "
                                  "is not extrapolated over the gap; the next measurement re-initialises it",
                             unit="s")

    def __post_init__(self) -> None:
        if self.max_frame_age < 0 or not self.motion_timeout > 0:
            raise ConfigError("max_frame_age must be >= 0 and motion_timeout positive", key="max_frame_age")
        require_positive(self, "max_pause")


@dataclass(frozen=True)
class InputLimitParams:
    """What the localizer believes of its motion and initial-pose inputs (anything beyond is dropped, warned)."""

    max_speed: float = param(3.0, "a cmd_vel or odom twist faster than this is dropped (a robot that drives "
                                  "faster must raise it: the gate opens with the speed)", unit="m/s")
    max_yaw_rate: float = param(3.0, "a cmd_vel or odom yaw rate above this is dropped", unit="rad/s")
    initial_pose_margin: float = param(10.0, "an initialpose farther than this outside the markers' extent "
                                             "(their x-y bounding box) is refused", unit="m")

    def __post_init__(self) -> None:
        require_positive(self, "max_speed", "max_yaw_rate")
        if not self.initial_pose_margin >= 0:
            raise ConfigError(f"must be >= 0, got {self.initial_pose_margin!r}", key="initial_pose_margin")


@dataclass(frozen=True)
class LocalizerOutputParams:
    """Frames and publishing of the localizer."""

    map_frame: str = param("", "frame of ~pose and the tf parent; empty: the map file's frame_id (map)")
    base_frame: str = param("", "the robot frame we publish; empty: the ring's base_frame (base_link)")
    odom_frame: str = param("odom", "odometry frame, for tf_mode map_to_odom and auto")
    publish_tf: bool = param(True, "broadcast our pose on tf")
    tf_mode: str = param("auto", "auto: map -> odom when odom -> base_link exists in tf, else map -> base_link "
                                 "(REP-105); map_to_odom; or map_to_base")
    markers_period: float = param(1.0, "publishing period of ~markers", unit="s")
    diagnostics_period: float = param(1.0, "publishing period of /diagnostics", unit="s")

    def __post_init__(self) -> None:
        if self.tf_mode not in TF_MODES:
            raise ConfigError(f"expected one of {TF_MODES}, got {self.tf_mode!r}", key="tf_mode")
        require_positive(self, "markers_period", "diagnostics_period")


@dataclass(frozen=True)
class LocalizerConfig:
    """Parameters of the localizer node and ``aruco_ring localize`` (config/localization.yaml)."""

    map_file: str = param("", "marker map YAML written by the mapper (required)")
    ring_file: str = param("", "ring YAML (cameras, namespaces, frames, fallback intrinsics and extrinsics); "
                               "empty: the package's config/ring.yaml")
    input: RingInputParams = section(RingInputParams, "the ring's detections, camera_info and extrinsics")
    estimator: LocalizationParams = section(LocalizationParams, "per-camera PnP, the paper's fusion or the joint "
                                                                "estimate (paper section II-E)")
    gate: GateParams = section(GateParams, "outlier gate against the prediction and the motion (paper Algorithm "
                                           "1, step 4)")
    filter: FilterParams = section(FilterParams, "the paper's Kalman filter: state x y x' y' x'' y'' phi phi' "
                                                 "phi'', measurement x y phi (paper section II-E-1)")
    tracker6: Tracker6Params = section(Tracker6Params, "the 6-DOF tracker of a rig that is not a ground robot "
                                                       "(used when filter/model is 6dof)")
    timing: TimingParams = section(TimingParams, "stale frames and motion inputs, pauses")
    limits: InputLimitParams = section(InputLimitParams, "physical limits of the motion inputs and initialpose")
    motion: MotionParams = section(MotionParams, "free-running cameras and odometry in the filter (issue 12; "
                                                 "docs/localization.md)")
    output: LocalizerOutputParams = section(LocalizerOutputParams, "frames and publishing")
    marker_check: MarkerCheckParams = section(MarkerCheckParams, "moved-marker detection: each marker against "
                                                                 "the pose from the others, over a window")


# --- mapper --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MarkerParams:
    """Marker sizes (aruco_detect's names)."""

    fiducial_len: float = param(0.20, "side of the black square of every marker (as aruco_detect)", unit="m")
    fiducial_len_override: str = param("", "per-id sides, aruco_detect syntax \"1-10: 0.05, 12: 0.06\"")

    def __post_init__(self) -> None:
        self.sizes()

    def sizes(self) -> MarkerSizes:
        """Marker sides per id (raises ConfigError naming the key)."""
        return MarkerSizes.parse(self.fiducial_len, self.fiducial_len_override)


@dataclass(frozen=True)
class MapParams:
    """What map is built and where it goes."""

    method: str = param("refined", "paper: the paper's chaining through the ring from the reference marker, "
                                   "averaged over frames; refined: that, then bundle adjustment")
    reference_marker: int = param(-1, "id fixing the map frame; -1: the paper's rule (the marker closest to its "
                                      "camera, most face-on, at the first placement)")
    map_frame: str = param("map", "name of the map frame (REP-105 map; aruco_map beside gmapping)")
    anchors_file: str = param("", "surveyed markers (YAML, docs/formats.md) that define the map frame: 2 or more "
                                  "markers' measured positions with their std, or one marker's pose; they enter "
                                  "the bundle adjustment as priors and the map records each one's residual; "
                                  "empty: the frame of reference_marker")
    boards_file: str = param("", "boards of markers with known layouts: a tagslam.yaml whose board / "
                                 "staggered_board bodies give them (docs/mapping.md, 'Boards'); a rigid board is "
                                 "one unknown of the bundle adjustment and places all its markers, a board whose "
                                 "tags have a play (the file's tag_position_noise / tag_rotation_noise) ties each "
                                 "tag to the layout by a prior of that std; empty: none")
    save_on_shutdown: bool = param(False, "save the map when the node stops")
    backups: int = param(5, "previous versions of the map file kept by every save: map.yaml.bak (the last), "
                            "map.yaml.bak.2, ... map.yaml.bak.N (the oldest); 0 keeps none")

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(f"expected one of {METHODS}, got {self.method!r}", key="method")
        if self.backups < 0:
            raise ConfigError(f"must be >= 0, got {self.backups!r}", key="backups")

    @property
    def reference(self) -> Optional[int]:
        """``reference_marker``, None for the paper's rule."""
        return self.reference_marker if self.reference_marker >= 0 else None


EXTRINSICS_KINDS = ("calibrated", "rough")


@dataclass(frozen=True)
class MapperCalibrationParams:
    """The mapper calibrating the ring from rough values while mapping (``aruco_ring calibrate-ring``'s
    method, docs/mapping.md)."""

    extrinsics: str = param("calibrated", "calibrated: the ring file's extrinsics are a calibration (the bundle "
                                          "adjustment refines them with priors of a few mm); rough: they are a "
                                          "drawing's values (off by up to ~5 cm and 10 deg per camera): ~save_map "
                                          "first calibrates every camera from the frames seen so far (the robot "
                                          "turning on the spot and driving among markers), writes the ring file "
                                          "(ring_file_out), publishes it on tf, then builds the map with it. "
                                          "mapping.launch's extrinsics:=rough sets this and leaves ring_tf out: the "
                                          "mapper then publishes base_link -> camK_optical_frame itself")
    ring_file_out: str = param("", "where the calibrated ring is written (atomic, previous kept as .bak); empty: "
                                   "beside the map file, <map file without .yaml>_ring.yaml")
    max_frames: int = param(400, "frames with markers used by the calibration, evenly spread over those kept")
    keep_frames: int = param(4000, "frames with markers kept for the calibration while mapping; at this many, "
                                   "every other one is dropped (memory stays bounded on a long run)")
    odometry: bool = param(True, "take the robot's odometry from tf (output/odom_frame -> the base frame) at "
                                 "each frame's stamp when it exists: it gives base_link's heading, which the "
                                 "images alone do not")

    def __post_init__(self) -> None:
        if self.extrinsics not in EXTRINSICS_KINDS:
            raise ConfigError(f"expected one of {EXTRINSICS_KINDS}, got {self.extrinsics!r}", key="extrinsics")
        if self.max_frames < 3:
            raise ConfigError(f"must be >= 3, got {self.max_frames!r}", key="max_frames")
        if self.keep_frames < self.max_frames:
            raise ConfigError(f"must be >= max_frames ({self.max_frames}), got {self.keep_frames!r}",
                              key="keep_frames")

    @property
    def rough(self) -> bool:
        return self.extrinsics == "rough"


@dataclass(frozen=True)
class MapperOutputParams:
    """Publishing and progress of the mapper."""

    publish_period: float = param(1.0, "how often a changed live (paper-mode) map is republished (~markers, "
                                       "fiducial_map, static tf map -> marker_<id>)", unit="s")
    progress_period: float = param(5.0, "how often progress goes to the log", unit="s")
    publish_tf: bool = param(True, "broadcast the robot's pose at its latest station in the live map (map -> odom "
                                   "or map -> base_link, as tf_mode says), so that the robot, its ring and its "
                                   "laser appear in the map while mapping")
    tf_mode: str = param("auto", "auto: map -> odom when odom -> base_link exists in tf, else map -> base_link "
                                 "(REP-105); map_to_odom; or map_to_base (beside gmapping, which owns map -> odom)")
    base_frame: str = param("", "the robot frame we publish; empty: the ring's base_frame (base_link)")
    odom_frame: str = param("odom", "odometry frame, for tf_mode map_to_odom and auto")
    tf_period: float = param(0.1, "how often that transform is broadcast (re-stamped)", unit="s")

    def __post_init__(self) -> None:
        require_positive(self, "publish_period", "progress_period", "tf_period")
        if self.tf_mode not in TF_MODES:
            raise ConfigError(f"expected one of {TF_MODES}, got {self.tf_mode!r}", key="tf_mode")


@dataclass(frozen=True)
class MapperConfig:
    """Parameters of the mapper node and ``aruco_ring build-map`` (config/mapping.yaml)."""

    map_file: str = param("", "where ~save_map writes (YAML, atomic, previous kept as .bak); empty: "
                              "$ROS_HOME/aruco_map.yaml")
    ring_file: str = param("", "ring YAML (camera names, namespaces, frames, extrinsics); empty: the package's "
                               "config/ring.yaml")
    # Mapping needs no low latency: a ring frame waits up to 1 s for a late camera (the live preview
    # holds the pipeline for 0.1-0.4 s on a loaded machine; a shorter wait split frames).
    input: RingInputParams = section(RingInputParams, "the ring's detections, camera_info and extrinsics",
                                     timeout=1.0)
    markers: MarkerParams = section(MarkerParams, "marker sizes")
    map: MapParams = section(MapParams, "the map built")
    mapping: MappingOptions = section(MappingOptions, "the map builder (paper section II-D and beyond)")
    calibration: MapperCalibrationParams = section(MapperCalibrationParams, "ring calibration from rough values "
                                                                        "while mapping")
    output: MapperOutputParams = section(MapperOutputParams, "publishing and progress")


# --- detector ------------------------------------------------------------------------------------

def _det(name: str):
    return default(DetectorParams, name)


@dataclass(frozen=True)
class DetectorConfig:
    """Parameters of the detector node (config/detector.yaml). Flat, with aruco_detect's names, so a
    launch file written for aruco_detect works unchanged."""

    dictionary: int = param(_det("dictionary"), "OpenCV predefined dictionary index: 7 = DICT_5X5_1000 "
                                                "(aruco_detect's default and the simulated lab's), 0 = DICT_4X4_50, "
                                                "16 = DICT_ARUCO_ORIGINAL, 17..20 = AprilTag families")
    fiducial_len: float = param(default(MarkerParams, "fiducial_len"), "side of the markers' black square, only used for fiducial_transforms (the "
                                      "mapper and localizer take sizes from their own configuration); the "
                                      "simulated lab's markers are 0.20 (aruco_detect's default is 0.14)", unit="m")
    fiducial_len_override: str = param("", "per-id sides: \"1-10: 0.05, 12: 0.06\"; empty: every marker is "
                                           "fiducial_len")
    ignore_fiducials: str = param("", "ids never published: \"1,4,9-12\"")
    publish_images: bool = param(False, "publish an annotated bgr8 image (outlines, ids, pose axes) on "
                                        "fiducial_images; costs a copy and a colour conversion per image")
    do_pose_estimation: bool = param(True, "publish fiducial_transforms (per-marker pose in the camera's optical "
                                           "frame with aruco_detect's image_error, object_error, fiducial_area); "
                                           "needs camera_info")
    corner_refinement: str = param(_det("corner_refinement"),
                                   "lines (unbiased edge-line intersections, 0.02-0.15 px on sharp markers) | "
                                   "subpix (exactly aruco_detect's corners) | contour | apriltag | none "
                                   "(docs/detector.md)")
    max_image_age: float = param(0.0, "drop images older than this when they arrive, 0 = off; keep 0 when "
                                      "replaying a bag without --clock (the stamps are then far in the past)",
                                 unit="s")
    image_transport: str = param("raw", "raw: subscribe image (sensor_msgs/Image); compressed: subscribe "
                                        "image/compressed (sensor_msgs/CompressedImage, image_transport's name)")
    tracking_full_every: int = param(5, "search the whole image every this many images; in between, only regions "
                                        "around the markers of the previous image and strips of tracking_edge_px "
                                        "along the left and right borders (a marker that is lost makes the same "
                                        "image searched whole); a new marker away from the side borders is found "
                                        "up to tracking_full_every - 1 images late (see "
                                        "tracking_windows_in_turn); 1 = every image whole (docs/detector.md)")
    tracking_edge_px: int = param(128, "width of the border strips searched in every image (markers come into "
                                       "view there as the robot turns), 0 = none", unit="px")
    tracking_windows_in_turn: bool = param(True, "the border strips and the scheduled whole-image searches with "
                                                 "ONE adaptive threshold window per search, the next one the next "
                                                 "time (the tracked markers' regions, and a search after a loss, "
                                                 "with all): 5.9 instead of 11.4 ms CPU per lab image (23 whole "
                                                 "image every time; bench_detector, load 12) at the same detections; "
                                                 "a new marker that only "
                                                 "some window finds (uneven light) may be found up to (number of "
                                                 "windows) searches later; false: all windows everywhere "
                                                 "(docs/detector.md)")
    adaptiveThreshWinSizeMin: int = param(_det("adaptive_thresh_win_size_min"),
                                          "smallest adaptive threshold window (aruco_detect's dynamic-reconfigure "
                                          "name); windows min, min+step, ... <= max are tried, each about 6 ms per "
                                          "1280x960 image", unit="px")
    adaptiveThreshWinSizeMax: int = param(_det("adaptive_thresh_win_size_max"), "largest threshold window",
                                          unit="px")
    adaptiveThreshWinSizeStep: int = param(_det("adaptive_thresh_win_size_step"),
                                           "window step; 5/21/16 (two windows) ran in 13 instead of 20 ms CPU with "
                                           "the same detections on the simulated lab (docs/detector.md); "
                                           "aruco_detect's own default 3/53/4 is robust in odd light but slow",
                                           unit="px")

    def __post_init__(self) -> None:
        if self.image_transport not in IMAGE_TRANSPORTS:
            raise ConfigError(f"expected one of {IMAGE_TRANSPORTS}, got {self.image_transport!r}",
                              key="image_transport")
        if self.max_image_age < 0:
            raise ConfigError(f"must be >= 0, got {self.max_image_age!r}", key="max_image_age")
        for key in ("tracking_full_every", "tracking_edge_px"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ConfigError(f"must be an integer >= 0, got {value!r}", key=key)
        self.detector_params()
        self.sizes()
        self.ignored()

    def detector_params(self) -> DetectorParams:
        """The core detector's settings (raises ConfigError naming the key)."""
        try:
            return DetectorParams(dictionary=self.dictionary, corner_refinement=self.corner_refinement,
                                  adaptive_thresh_win_size_min=self.adaptiveThreshWinSizeMin,
                                  adaptive_thresh_win_size_max=self.adaptiveThreshWinSizeMax,
                                  adaptive_thresh_win_size_step=self.adaptiveThreshWinSizeStep)
        except ConfigError as exc:
            names = {"adaptive_thresh_win_size_min": "adaptiveThreshWinSizeMin",
                     "adaptive_thresh_win_size_max": "adaptiveThreshWinSizeMax",
                     "adaptive_thresh_win_size_step": "adaptiveThreshWinSizeStep"}
            raise ConfigError(exc.detail, key=names.get(exc.key or "", exc.key)) from None

    def sizes(self) -> MarkerSizes:
        """Marker sides per id (raises ConfigError naming fiducial_len / fiducial_len_override)."""
        return MarkerSizes.parse(self.fiducial_len, self.fiducial_len_override)

    def ignored(self) -> frozenset:
        """Ids never published (raises ConfigError naming ignore_fiducials)."""
        return frozenset(parse_id_list(self.ignore_fiducials, key="ignore_fiducials"))


# --- ring_tf -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RingTfConfig:
    """Parameters of the ring_tf node (set by launch/ring_tf.launch's arguments)."""

    ring_file: str = param("", "ring YAML; one static transform base_link -> camK_optical_frame per camera, all "
                               "in one /tf_static message; empty: the package's config/ring.yaml")
    map_file: str = param("", "a marker map: when it carries a ring_calibration (the extrinsics refined while "
                              "mapping), those are published instead of the ring file's; empty: none")
    frustum_depth: float = param(1.0, "length of each camera's field of view drawn on ~markers (rviz)", unit="m")

    def __post_init__(self) -> None:
        require_positive(self, "frustum_depth")


# --- apriltag_relay ------------------------------------------------------------------------------

@dataclass(frozen=True)
class ApriltagRelayConfig:
    """Parameters of the apriltag_relay node (set by launch/apriltag_relay.launch's arguments)."""

    ring_file: str = param("", "ring YAML (cameras, namespaces, frame_ids; intrinsics for apriltag_ros poses when "
                               "no camera_info); empty: the package's config/ring.yaml")
    cameras: Tuple[str, ...] = param([], "ring cameras to relay (cam0 cam1); empty: all of the ring")
    input_topics: Tuple[str, ...] = param(["tags", "tag_detections"], "detection topics relative to each camera's "
                                                                      "namespace (either message type on any)")
    ignore_fiducials: str = param("", "ids never relayed, aruco_detect syntax \"1,4,9-12\"")
    fiducial_len: float = param(0.2, "tag side the mapper / localizer use (apriltag_ros's sizes are checked "
                                     "against it)", unit="m")
    fiducial_len_override: str = param("", "per-id sizes, aruco_detect syntax \"1-10: 0.05, 12: 0.1\"")
    tagslam_file: str = param("", "a TagSLAM tagslam.yaml whose tag sizes are used (fiducial_len_override still "
                                  "wins)")

    def __post_init__(self) -> None:
        require_positive(self, "fiducial_len")
        parse_id_list(self.ignore_fiducials, key="ignore_fiducials")


# --- comparison ----------------------------------------------------------------------------------

def _cmp(name: str):
    return default(_comparison.ComparisonConfig, name)


@dataclass(frozen=True)
class ComparisonConfig:
    """Parameters of the comparison node (config/comparison.yaml)."""

    reference_frame: str = param("map", "the reference robot pose is reference_frame -> reference_child (gmapping: "
                                        "map -> base_link; in the simulation the ground truth, world -> "
                                        "sim_ground_truth)")
    reference_child: str = param("base_link", "see reference_frame")
    estimate_frame: str = param("aruco_map", "ours is estimate_frame -> estimate_child (localization.launch "
                                             "beside_gmapping:=true publishes aruco_map -> aruco_base_link)")
    estimate_child: str = param("aruco_base_link", "see estimate_frame")
    rate: float = param(10.0, "rate at which our latest pose is paired with the reference at the same stamp",
                        unit="Hz")
    lookup_timeout: float = param(0.2, "time to wait for the reference pose at our stamp before skipping the pair",
                                  unit="s")
    alignment: Tuple[float, ...] = param([], "[x, y, yaw_deg], the pose of estimate_frame in reference_frame, when "
                                             "you know it (measured once); empty: estimated by SE(2) least squares "
                                             "over all pose pairs (closed form; a fitted alignment absorbs any "
                                             "constant offset between the two systems)")
    min_pairs: int = param(_cmp("min_pairs"), "pose pairs needed before the alignment is estimated and errors are "
                                              "published")
    max_pairs: int = param(_cmp("max_pairs"), "pairs used for the alignment (older ones are thinned evenly in time)")
    publish_tf: bool = param(True, "publish reference_frame -> estimate_frame (map -> aruco_map) so rviz shows both "
                                   "robots in the reference map")
    still_time: float = param(_cmp("still_time"), "time the reference must stay still to record a stop (a row of "
                                                  "Table I / II) automatically; <= 0: only the ~record_stop service "
                                                  "records stops", unit="s")
    still_position_tolerance: float = param(_cmp("still_position_tolerance"), "what still means, position",
                                            unit="m")
    still_yaw_tolerance_deg: float = param(float(np.degrees(_cmp("still_yaw_tolerance"))), "what still means, yaw",
                                           unit="deg")
    settle: float = param(_cmp("settle"), "time ignored at the start of a still period (the filters catching up "
                                          "after the motion)", unit="s")
    record_window: float = param(_cmp("record_window"), "time of pose pairs averaged by a ~record_stop request",
                                 unit="s")
    output_dir: str = param("", "where Table I/II (table1.md/.csv, table2.md/.csv, comparison_summary.json) are "
                                "written at shutdown and on ~write_tables; empty: $ROS_HOME/comparison")
    reference_name: str = param("gmapping", "how the tables name the reference")
    text_height: float = param(1.5, "height above the reference robot of the rviz text (~text)", unit="m")

    def __post_init__(self) -> None:
        self.core_config()

    def core_config(self) -> "_comparison.ComparisonConfig":
        """The comparison core's settings (raises ConfigError naming ``alignment``)."""
        alignment = None
        if self.alignment:
            if len(self.alignment) != 3:
                raise ConfigError(f"expected [x, y, yaw_deg], got {list(self.alignment)!r}", key="alignment")
            x, y, yaw = (float(v) for v in self.alignment)
            alignment = (x, y, float(np.radians(yaw)))
        return _comparison.ComparisonConfig(
            alignment=alignment, min_pairs=self.min_pairs, max_pairs=self.max_pairs, still_time=self.still_time,
            still_position_tolerance=self.still_position_tolerance,
            still_yaw_tolerance=float(np.radians(self.still_yaw_tolerance_deg)), settle=self.settle,
            record_window=self.record_window)


#: node name -> (schema, YAML file under config/ or None): what the docs and the consistency test cover.
NODE_SCHEMAS = {
    "localizer": (LocalizerConfig, "localization.yaml"),
    "mapper": (MapperConfig, "mapping.yaml"),
    "detector": (DetectorConfig, "detector.yaml"),
    "ring_tf": (RingTfConfig, None),
    "apriltag_relay": (ApriltagRelayConfig, None),
    "comparison": (ComparisonConfig, "comparison.yaml"),
}
