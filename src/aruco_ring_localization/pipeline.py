"""The one localization pipeline and the one mapping pipeline, without ROS.

Everything between "a camera's detections arrive" and "a pose goes out" (or "the map is saved")
lives here, once. The ``localizer`` node, ``aruco_ring localize``, the benchmarks and the demo
drive :class:`LocalizationPipeline`; the ``mapper`` node and ``aruco_ring build-map`` drive
:class:`MappingPipeline`. They only convert messages into the event calls below and publish
what the calls return, so a recorded bag replayed offline gives exactly the node's poses.

Events (each takes ``now``, the caller's clock in seconds: ROS time in a node, the bag's
receive time offline; outputs depend only on the sequence of events and their ``now``)::

    on_camera_info(camera, model)            intrinsics of a camera (its camera_info)
    on_extrinsics(camera, T_base_cam)        extrinsics (tf; None = the ring file's)
    on_detections(camera, stamp, obs, now)   one camera's detections -> [PoseOutput]
    on_motion(source, stamp, v_xy, w, now)   cmd_vel or odom twist -> []
    on_initial_pose(T_or_se2, now)           rviz "2D Pose Estimate" -> []
    reset()                                  forget the track
    poll(now)                                timed-out ring frames, predict-only output -> [PoseOutput]

Per detection message (:class:`RingInput`): the stamp policy (:meth:`RingInput.check_stamp`),
the calibration in force (camera_info models, extrinsics), sanitizing (ONCE, here:
:func:`detections.sanitize_observations`), ring-frame assembly (:class:`RingFrameAssembler`).
Per ring frame (:meth:`LocalizationPipeline._track`, paper Algorithm 1, steps 2-5): the time-jump
policy, the filter's prediction seeds :class:`RingLocalizer`, the measurement goes through
:class:`MotionGate` with the latest motion input, then :class:`PoseFilter` (update,
re-initialisation or predict only). Stale ring frames are dropped (``timing.max_frame_age``),
and while every camera is silent :meth:`LocalizationPipeline.poll` publishes the filter's
prediction with its growing covariance.

Per-message problems are logged through :mod:`logging` with a throttle that is part of the core
(:class:`throttle.ThrottledWarnings`, one line per problem per 5 s of ``now``); the nodes send
these records to rosout. Nothing here is thread-safe: a node calls a pipeline under one lock.
"""
from __future__ import annotations

import logging
import math
import os
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Deque, Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .anchors import load_anchors
from .camera import CameraModel
from .detections import CameraFrame, MarkerObservation, RingFrame, RingFrameAssembler, sanitize_observations
from .errors import ConfigError, GeometryError, MeasurementError
from .gating import REJECTED_AMBIGUOUS, REJECTED_JUMP, REJECTED_TILT, GateDecision, MotionGate
from .kalman import PoseFilter
from .localization import se2_covariance
from .tracker6 import Tracker6, move_pose
from .localization import LazyMapping, LocalizationResult, RingLocalizer
from .mapping import MapBuilder
from .marker_check import MarkerCheck
from .marker_map import MarkerMap
from .odometry import (OdometryHistory, OdometryHistory6, constant_velocity_displacement, propagate_se2, psd_factor,
                       se2_between)
from .ring import CameraRing, apply_refined_extrinsics
from .ring_calibration import CalibrationOptions, RingCalibration, calibrate_ring
from .schemas import LocalizerConfig, MapperConfig, RingInputParams
from .throttle import WARN_PERIOD, ThrottledWarnings

logger = logging.getLogger(__name__)

#: Reasons a whole camera frame is skipped (keys of :attr:`RingInput.skipped`).
SKIP_NO_CAMERA_INFO = "no camera_info"
SKIP_NO_EXTRINSICS = "no extrinsics"
SKIP_BAD_STAMP = "bad stamp"
SKIP_FUTURE_STAMP = "future stamp"
SKIP_STALE_STAMP = "stale stamp"
SKIP_FLOOD = "too many detections"

#: Motion inputs :meth:`LocalizationPipeline.on_motion` takes.
MOTION_SOURCES = ("cmd_vel", "odom")
#: Reason an odometry pose is not used for prediction (``rejected_odom_pose_jump``).
ODOM_POSE_JUMP = "pose jump"


def resolve_camera_names(ring: CameraRing, entries: Optional[Sequence[str]]) -> List[str]:
    """Ring camera names from a list of names (``cam0``) or namespaces (``ring/cam0``).

    Empty -> every ring camera. Raises ConfigError naming an entry that matches nothing.
    """
    if not entries:
        return ring.names
    by_ns = {c.namespace.strip("/"): c.name for c in ring.cameras}
    out = []
    for e in entries:
        e = str(e).strip()
        if e in ring.names:
            out.append(e)
        elif e.strip("/") in by_ns:
            out.append(by_ns[e.strip("/")])
        else:
            raise ConfigError(f"camera {e!r} is neither a ring camera name {ring.names} nor a namespace "
                              f"{sorted(by_ns)}", key="input.cameras")
    return out


#: (x, y, yaw)'s rows and columns in a 6x6 pose covariance (index arrays for one assignment).
_SE2_ROWS, _SE2_COLS = np.ix_([0, 1, 5], [0, 1, 5])


def pose_covariance_from_se2(cov3: np.ndarray, z_var: float = 1e6, rp_var: float = 1e6) -> np.ndarray:
    """(x, y, yaw) 3x3 covariance -> 6x6 over (x, y, z, roll, pitch, yaw) (PoseWithCovariance order).

    z, roll and pitch are not estimated: they get a large variance, so robot_localization
    ignores them (its ``two_d_mode`` users configure them out anyway).
    """
    C = np.zeros((6, 6))
    C[_SE2_ROWS, _SE2_COLS] = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    C[2, 2] = z_var
    C[3, 3] = C[4, 4] = rp_var
    return C


# --- the way in: stamps, calibration in force, sanitizing, assembly -----------------------------

class RingInput:
    """Per-camera detections -> ring frames, with the calibration in force.

    Args:
        ring: the calibrated ring (names, frames, fallback intrinsics and extrinsics).
        params: the ``input`` section of the node's schema.
        warn: the pipeline's throttled warnings.
        label: how the warnings name this stage.
        max_age: a message stamped longer than this (s) before the node's clock is dropped as
            stale (the localizer's ``timing.max_frame_age``); 0: no limit (the mapper).
    """

    def __init__(self, ring: CameraRing, params: RingInputParams, warn: ThrottledWarnings,
                 label: str = "ring input", max_age: float = 0.0):
        self.params = params
        self.max_age = float(max_age)
        self.calibrated_ring = ring
        self.camera_names = resolve_camera_names(ring, params.cameras)
        self.ignore_ids = params.ignored_ids()
        self.assembler = RingFrameAssembler(self.camera_names, slop=params.slop, timeout=params.timeout,
                                            silence=params.silent_after, late_by_clock=self.max_age > 0)
        self._warn = warn
        self._label = label
        self._models: Dict[str, CameraModel] = {}
        self._extrinsics: Dict[str, np.ndarray] = (
            {} if params.use_tf else {n: ring[n].T_base_cam for n in self.camera_names})
        self._ring = ring
        #: camera -> {reason: count} of detections dropped by sanitize_observations.
        self.rejected: Dict[str, Dict[str, int]] = {n: {} for n in self.camera_names}
        #: camera -> {reason: count} of whole camera frames skipped (no camera_info / extrinsics / stamp).
        self.skipped: Dict[str, Dict[str, int]] = {n: {} for n in self.camera_names}
        self.frames_in = 0
        self.ring_frames_out = 0

    # --- calibration in force ---------------------------------------------------------------

    def set_camera_model(self, camera: str, model: CameraModel) -> None:
        """The intrinsics from this camera's latest camera_info."""
        self._models[camera] = model

    def camera_model(self, camera: str) -> Optional[CameraModel]:
        """Intrinsics in force for ``camera`` (camera_info, or the ring's with the fallback), or None."""
        model = self._models.get(camera)
        if model is None and self.params.camera_info_fallback:
            model = self.calibrated_ring[camera].model
        return model

    def set_extrinsics(self, camera: str, T_base_cam: Optional[np.ndarray] = None) -> None:
        """``T_base_cam`` (4x4) of ``camera`` (from tf); None: the calibrated ring's."""
        if camera not in self.skipped:
            raise ConfigError(f"extrinsics for {camera}, which is not an input camera ({self.camera_names})",
                              key="input.cameras")
        T = self.calibrated_ring[camera].T_base_cam if T_base_cam is None else \
            geo.validate_transform(T_base_cam, f"extrinsics of {camera}")
        self._extrinsics[camera] = T
        self._ring = self.calibrated_ring.with_extrinsics(self._extrinsics)

    def has_extrinsics(self, camera: str) -> bool:
        return camera in self._extrinsics

    @property
    def ring(self) -> CameraRing:
        """The ring with the extrinsics in force (tf's where known, the file's for the others)."""
        return self._ring

    # --- data -------------------------------------------------------------------------------

    def check_stamp(self, source: str, stamp: float, now: float) -> Optional[str]:
        """Why a message of ``source`` (a camera, ``odom``) stamped ``stamp`` must not be used at
        ``now`` (the node's clock), or None. THE stamp policy of the package:

        * not finite: ``SKIP_BAD_STAMP``;
        * more than ``input.max_stamp_ahead`` after ``now``: ``SKIP_FUTURE_STAMP`` (a future stamp
          would make the filter predict to it and put the pose on tf at it);
        * more than ``max_age`` before ``now`` (when set): ``SKIP_STALE_STAMP`` (it can only make
          a ring frame the localizer drops as stale, and it must not pass for a clock jump; ROS's
          "no stamp", 0, is one of these).

        A clock that jumps back (a bag loop) moves ``now`` with the stamps: nothing is dropped.
        """
        if not math.isfinite(stamp):   # (math's: np.isfinite of a float costs ~0.6 us, every message)
            return SKIP_BAD_STAMP
        if stamp - now > self.params.max_stamp_ahead:
            return SKIP_FUTURE_STAMP
        if self.max_age > 0 and now - stamp > self.max_age:
            return SKIP_STALE_STAMP
        return None

    def stamp_hint(self, reason: str, stamp: float, now: float) -> str:
        """The offset a stamp warning names (`` (+282.1 s ahead of the clock ...)``)."""
        if reason == SKIP_FUTURE_STAMP:
            return f" ({stamp - now:+.3f} s ahead of the node's clock; input/max_stamp_ahead {self.params.max_stamp_ahead} s)"
        if reason == SKIP_STALE_STAMP:
            return f" ({now - stamp:.3f} s old by the node's clock; limit {self.max_age} s)"
        return f" ({stamp!r})"

    def topic(self, camera: str) -> str:
        """The detection topic of ``camera`` (relative to the node's namespace), for warnings."""
        ns = self.calibrated_ring[camera].namespace.strip("/") if camera in self.skipped else ""
        return f"{ns}/fiducial_vertices" if ns else "fiducial_vertices"

    def add_detections(self, camera: str, stamp: float, observations: Sequence[MarkerObservation],
                       now: float) -> List[RingFrame]:
        """Take one camera's detections at ``stamp`` (s); return the ring frames ready to go out.

        Each camera frame keeps its own stamp (``RingFrame.cameras[c].stamp``; the ring frame's is
        the earliest), for an estimator that compensates free-running cameras (issue 12).
        """
        self.frames_in += 1
        if camera not in self.skipped:
            self._warn(f"unknown camera {camera}", f"{self._label}: detections from {camera!r}, which is not an "
                                                   f"input camera {self.camera_names}: ignored", now)
            return self.poll(now)
        model = self.camera_model(camera)
        reason = self.check_stamp(camera, stamp, now)
        hint = "" if reason is None else self.stamp_hint(reason, stamp, now)
        if reason is None and len(observations) > self.params.max_detections:
            reason, hint = SKIP_FLOOD, f" (more than input/max_detections {self.params.max_detections})"
        if reason is None and model is None:
            reason, hint = SKIP_NO_CAMERA_INFO, " (set input/camera_info_fallback: true to use the ring file's)"
        if reason is None and camera not in self._extrinsics:
            reason, hint = SKIP_NO_EXTRINSICS, (f" (tf {self.calibrated_ring.base_frame} -> "
                                                f"{self.calibrated_ring[camera].frame_id})")
        if reason is not None:
            counts = self.skipped[camera]
            counts[reason] = counts.get(reason, 0) + 1
            self._warn(f"{camera}.{reason}", f"{self._label}: {camera} ({self.topic(camera)}): {reason}{hint}; "
                                             "skipping its detections", now)
            return self.poll(now)
        kept, dropped = sanitize_observations(observations, self.ignore_ids, model.width, model.height)
        if dropped:
            counts = self.rejected[camera]
            for k, v in dropped.items():
                counts[k] = counts.get(k, 0) + v
            bad = {k: v for k, v in dropped.items() if k != "ignored"}
            if bad:
                self._warn(f"{camera}.malformed", f"{self._label}: {camera}: dropped malformed detections {bad}", now)
        out = self.assembler.add(CameraFrame(camera, float(stamp), kept, model), now)
        self.ring_frames_out += len(out)
        return out

    def incomplete_reasons(self) -> str:
        """Why ring frames went out without every camera, e.g. "3 after input/timeout, 1 overtaken"."""
        names = {"timeout": "after input/timeout", "silent": "cameras silent for input/silent_after",
                 "overtaken": "overtaken by a newer frame"}
        parts = [f"{n} {names[k]}" for k, n in self.assembler.incomplete.items() if n]
        return ", ".join(parts) or "flushed at the end"

    def poll(self, now: float, flush: bool = False) -> List[RingFrame]:
        """Ring frames whose timeout has expired at ``now``; with ``flush`` every pending one."""
        out = self.assembler.poll(np.inf if flush else now)
        self.ring_frames_out += len(out)
        return out

    def silent_cameras(self, now: float) -> List[str]:
        """Cameras from which nothing usable has arrived for ``input.silent_after`` s (or ever)."""
        return self.assembler.silent_cameras(now, self.params.silent_after)


class _RingPipeline:
    """What both pipelines share: the way in (:attr:`input`), the calibration events, the warnings."""

    input: RingInput
    warn: ThrottledWarnings

    def on_camera_info(self, camera: str, model: CameraModel) -> None:
        """The intrinsics of ``camera`` from its camera_info."""
        self.input.set_camera_model(camera, model)

    def on_extrinsics(self, camera: str, T_base_cam: Optional[np.ndarray] = None) -> None:
        """``T_base_cam`` of ``camera`` (tf); None: the calibrated ring's (the ring file's; for
        localization refined with the map)."""
        self.input.set_extrinsics(camera, T_base_cam)
        self._use_ring(self.input.ring)

    def _use_ring(self, ring: CameraRing) -> None:
        """Hand the ring with the extrinsics in force to the estimator / map builder."""
        raise NotImplementedError

    @property
    def ring(self) -> CameraRing:
        """The ring with the extrinsics in force."""
        return self.input.ring

    @property
    def camera_names(self) -> List[str]:
        return list(self.input.camera_names)


# --- localization ---------------------------------------------------------------------------------

@dataclass
class TrackResult:
    """One ring frame through the estimator, the gate and the filter.

    Attributes:
        stamp: s. localization: the per-frame result. decision: the gate's (None if no pose).
        pose: filtered (x, y, yaw), or None before the first measurement.
        covariance: 3x3 filter covariance of (x, y, yaw), or None.
        time_jump: the filter was reset because time went backwards.
        T_map_base: (4, 4) the 6-DOF tracker's filtered pose (``filter/model: 6dof``), else None.
    """

    stamp: float
    localization: LocalizationResult
    decision: Optional[GateDecision] = None
    pose: Optional[np.ndarray] = None
    covariance: Optional[np.ndarray] = None
    time_jump: bool = False
    T_map_base: Optional[np.ndarray] = None


@dataclass
class PoseOutput:
    """What the localizer publishes for one ring frame (or one predict-only step).

    Attributes:
        stamp: s (the ring frame's; ``now`` for a prediction).
        T_map_base: (4, 4) the filtered planar pose at the measured height (``~pose``, tf).
        T_map_base_6dof: (4, 4) the same with the last accepted measurement's roll and pitch.
        covariance: (6, 6) over (x, y, z, roll, pitch, yaw), REP-103 order.
        twist: (3,) body-frame (v_forward m/s, v_left m/s, yaw rate rad/s) of the filter.
        twist_covariance: (6, 6), same layout.
        camera_estimates: camera -> (4, 4) ``T_map_base`` of each valid per-camera estimate.
        track: the ring frame through the pipeline (the measurement is ``track.localization``).
        predicted_only: no ring frame: every camera silent, the filter's prediction.
        from_odometry: the filter predicted to an odometry message's stamp (``motion.odometry``:
            the pose at the odometry rate); no measurement, no camera estimates.
    """

    stamp: float
    T_map_base: np.ndarray
    T_map_base_6dof: np.ndarray
    covariance: np.ndarray
    twist: np.ndarray
    twist_covariance: np.ndarray
    camera_estimates: Dict[str, np.ndarray]
    track: TrackResult
    predicted_only: bool = False
    from_odometry: bool = False


@dataclass
class StatusReport:
    """One diagnostics status (the node makes a diagnostic_msgs/DiagnosticStatus of it)."""

    name: str
    hardware_id: str
    ok: bool
    message: str
    values: List[Tuple[str, str]] = field(default_factory=list)


@dataclass
class _Motion:
    speed: float = 0.0
    yaw_rate: float = 0.0
    stamp: float = -np.inf


class LocalizationPipeline(_RingPipeline):
    """Detections (+ camera_info, extrinsics, motion) in, filtered poses out (module docstring).

    Args:
        config: the localizer's schema (config/localization.yaml).
        ring: the calibrated ring (the ring file); when the map carries extrinsics refined while
            mapping, they replace the ring file's (what ring_tf publishes with that map).
        marker_map: the map; its frame is the output frame.

    Raises:
        ConfigError: an empty map, a refined calibration for another ring, a camera list that
            names no ring camera.
    """

    def __init__(self, config: LocalizerConfig, ring: CameraRing, marker_map: MarkerMap):
        if len(marker_map) == 0:
            raise ConfigError("the map has no markers", path=config.map_file or None, key="markers")
        if marker_map.ring_extrinsics:
            ring = apply_refined_extrinsics(ring, marker_map.ring_extrinsics, marker_map.ring_base_frame,
                                            source=config.map_file or "<map>")
            logger.info("using the ring extrinsics refined while mapping (%s) where tf gives none",
                        config.map_file or "the map")
        self.config = config
        self.marker_map = marker_map
        self.warn = ThrottledWarnings(logger.warning, WARN_PERIOD)
        self.input = RingInput(ring, config.input, self.warn, label="localizer",
                               max_age=config.timing.max_frame_age)
        self.localizer = RingLocalizer(self.input.ring, marker_map, config.estimator)
        self.gate = MotionGate(config.gate)
        self.filter = PoseFilter(config.filter)
        #: ``filter/model: 6dof``: the 6-DOF tracker replaces the gate and the planar filter.
        self.tracker6 = Tracker6(config.tracker6) if config.filter.model == "6dof" else None
        #: moved-marker detection (marker_check.py), None when marker_check.enabled is false.
        self.marker_check = MarkerCheck(marker_map, config.marker_check, self.warn,
                                        extrinsic_jitter=np.radians(config.estimator.extrinsic_jitter_deg)) \
            if config.marker_check.enabled else None
        self._motion: Dict[str, _Motion] = {}
        #: Odometry poses (and IMU yaw) by stamp, with ``motion.odometry`` (issue 12).
        self.odometry = OdometryHistory(config.motion)
        #: ... and the full 6-DOF poses for the 6-DOF tracker (``filter/model: 6dof``).
        self.odometry6 = OdometryHistory6(config.motion)
        self.odometry_outputs = 0
        self._z = 0.0                        # height of base_link in the map (last accepted measurement)
        self._roll_pitch = (0.0, 0.0)        # ... and its roll, pitch
        self._last_stamp: Optional[float] = None
        self._last_frame_now: Optional[float] = None
        self._clock: Optional[float] = None          # the latest ``now`` of any event (the node's clock)
        self._clock_jumped = False                   # the clock went back: the next track says time_jump
        self._frame_velocity: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None   # _motion_model's
        xy = np.array([e.T_map_marker[:2, 3] for e in marker_map])
        #: (x_min, y_min, x_max, y_max) of the markers in the map frame: where an initialpose may lie (+ margin).
        self.extent = (*xy.min(axis=0), *xy.max(axis=0))
        self.last_update_now: Optional[float] = None
        self.last_track: Optional[TrackResult] = None
        # counters (diagnostics)
        self.frames = 0
        self.dropped_stale = 0
        self.predicted_only = 0
        self.frames_missing = 0             # ring frames processed without every camera
        self.time_jumps = 0
        self.pauses = 0                     # clock gaps longer than timing.max_pause (re-initialisations)
        self.rejected_counts: Dict[str, int] = {}
        self.latency_ms: Deque[float] = deque(maxlen=200)
        self._camera_stats: Dict[str, Dict[str, float]] = {}
        self._in_view: Dict[int, float] = {}

    # --- events -----------------------------------------------------------------------------

    def _use_ring(self, ring: CameraRing) -> None:
        self.localizer.set_ring(ring)

    def on_detections(self, camera: str, stamp: float, observations: Sequence[MarkerObservation],
                      now: float) -> List[PoseOutput]:
        """One camera's detections (raw pixels) at ``stamp``; returns the poses to publish."""
        self._tick(now)
        return self._process(self.input.add_detections(camera, stamp, observations, now), now)

    def on_motion(self, source: str, stamp: Optional[float], linear_xy: Sequence[float], yaw_rate: float,
                  now: float, T_odom_base: Optional[np.ndarray] = None) -> List[PoseOutput]:
        """A motion input: ``cmd_vel`` (no stamp) or ``odom`` (its header stamp and twist).

        Args:
            source: ``cmd_vel`` or ``odom``.
            stamp: the message's stamp (s), or None (Twist has none; 0 counts as none): ``now``.
            linear_xy: (v_x, v_y) m/s; yaw_rate: rad/s, body frame.
            T_odom_base: the odometry pose (4x4) of base_link in odom. With ``motion.odometry``
                it goes into :attr:`odometry` and the filter is predicted to ``stamp`` with the
                increment since its own stamp: the pose at the odometry rate is returned.

        The gate allows jumps that grow with the largest fresh speed. Dropped, with a throttled
        warning naming the source: a non-finite speed; a speed or yaw rate beyond ``limits``; a
        stamp the stamp policy refuses (:meth:`RingInput.check_stamp`: in the future, or older
        than ``timing.motion_timeout``). A kept input is fresh for ``timing.motion_timeout`` s of
        the node's clock from its stamp, never from later than its arrival.
        """
        if source not in MOTION_SOURCES:
            raise ValueError(f"motion source must be one of {MOTION_SOURCES}, got {source!r}")
        self._tick(now)
        v = float(np.hypot(float(linear_xy[0]), float(linear_xy[1])))
        w = float(yaw_rate)
        t = float(stamp) if stamp else float(now)
        lim = self.config.limits
        problem = None
        if not (np.isfinite(v) and np.isfinite(w)):
            key, problem = "non-finite", f"non-finite speed (v {v!r}, yaw rate {w!r})"
        elif v > lim.max_speed or abs(w) > lim.max_yaw_rate:
            key, problem = "beyond limits", (f"speed {v:.3g} m/s / yaw rate {w:.3g} rad/s beyond limits/max_speed "
                                             f"{lim.max_speed} m/s / limits/max_yaw_rate {lim.max_yaw_rate} rad/s")
        else:
            key = self.input.check_stamp(source, t, now)
            if key == SKIP_STALE_STAMP or (key is None and now - t > self.config.timing.motion_timeout):
                key = SKIP_STALE_STAMP
                problem = f"stale stamp ({now - t:.3f} s old by the node's clock > timing/motion_timeout)"
            elif key is not None:
                problem = f"{key}{self.input.stamp_hint(key, t, now)}"
        if problem is not None:
            self.rejected_counts[f"{source}_{key.replace(' ', '_')}"] = \
                self.rejected_counts.get(f"{source}_{key.replace(' ', '_')}", 0) + 1
            self.warn(f"{source}.{key}", f"localizer: {source}: {problem}: ignored", now)
            return []
        self._motion[source] = _Motion(abs(v), abs(w), min(t, float(now)))
        if source != "odom" or not self.config.motion.odometry or T_odom_base is None:
            return []
        return self._on_odometry_pose(t, T_odom_base, now)

    def on_imu(self, stamp: Optional[float], yaw_rate: float, now: float) -> List[PoseOutput]:
        """An IMU's yaw rate (sensor_msgs/Imu ``angular_velocity.z``, rad/s) at ``stamp``.

        Used with ``motion.imu`` only: the odometry increments take their yaw from the integrated
        rate. Validated as the other motion inputs: finite, within ``limits.max_yaw_rate``, a stamp
        the stamp policy accepts and not older than ``timing.motion_timeout``; else dropped with a
        throttled warning naming ``imu``.
        """
        self._tick(now)
        if not self.config.motion.imu:
            return []
        w = float(yaw_rate)
        t = float(stamp) if stamp else float(now)
        lim = self.config.limits
        problem = None
        if not np.isfinite(w):
            key, problem = "non-finite", f"non-finite yaw rate {w!r}"
        elif abs(w) > lim.max_yaw_rate:
            key, problem = "beyond limits", f"yaw rate {w:.3g} rad/s beyond limits/max_yaw_rate {lim.max_yaw_rate} rad/s"
        else:
            key = self.input.check_stamp("imu", t, now)
            if key == SKIP_STALE_STAMP or (key is None and now - t > self.config.timing.motion_timeout):
                key = SKIP_STALE_STAMP
                problem = f"stale stamp ({now - t:.3f} s old by the node's clock > timing/motion_timeout)"
            elif key is not None:
                problem = f"{key}{self.input.stamp_hint(key, t, now)}"
        if problem is None and not self.odometry.add_yaw_rate(t, w):
            key, problem = "out of order", "stamp not after the previous imu message"
        if problem is not None:
            name = f"imu_{key.replace(' ', '_')}"
            self.rejected_counts[name] = self.rejected_counts.get(name, 0) + 1
            self.warn(f"imu.{key}", f"localizer: imu: {problem}: ignored", now)
        return []

    def _on_odometry_pose(self, t: float, T_odom_base: np.ndarray, now: float) -> List[PoseOutput]:
        """Keep an odometry pose; predict the filter to it and return the pose (``motion.odometry``).

        The pose must be a valid transform and must not jump: between two messages within
        ``motion.max_gap`` it may move at most ``limits.max_speed`` (and turn at most
        ``limits.max_yaw_rate``; for the 6-DOF tracker the angle of its full rotation) times the
        stamps' difference, plus 2 cm / 2 deg; otherwise the history restarts from it (nothing is
        predicted across the jump) with a throttled warning.
        """
        try:
            se2 = geo.se2_from_transform(geo.validate_transform(T_odom_base, "odom pose"))
        except (GeometryError, ValueError) as exc:
            self.rejected_counts["odom_bad_pose"] = self.rejected_counts.get("odom_bad_pose", 0) + 1
            self.warn("odom.bad pose", f"localizer: odom: pose.pose: {exc}: not used for prediction", now)
            return []
        if not np.all(np.isfinite(se2)):
            self.rejected_counts["odom_bad_pose"] = self.rejected_counts.get("odom_bad_pose", 0) + 1
            self.warn("odom.bad pose", "localizer: odom: pose.pose not finite: not used for prediction", now)
            return []
        # The 6-DOF tracker keeps the full pose (predicted along at the next ring frame, _track6).
        last = (self.odometry if self.tracker6 is None else self.odometry6).latest_stamp
        if last is not None and t <= last:
            self.rejected_counts["odom_out_of_order"] = self.rejected_counts.get("odom_out_of_order", 0) + 1
            self.warn("odom.out of order", f"localizer: odom: stamp {t:.3f} s not after the previous {last:.3f} s: "
                                           "pose not used for prediction", now)
            return []
        six = self.tracker6 is not None
        history = self.odometry6 if six else self.odometry
        if last is not None and t - last <= self.config.motion.max_gap:
            jump = self._odometry_jump(last, t, T_odom_base if six else se2)
            if jump is not None:
                dist, angle = jump
                key = f"odom_{ODOM_POSE_JUMP.replace(' ', '_')}"
                self.rejected_counts[key] = self.rejected_counts.get(key, 0) + 1
                self.warn("odom.pose jump", f"localizer: odom: pose.pose jumped {dist:.3f} m / "
                                            f"{np.degrees(angle):.1f} deg in {t - last:.3f} s (beyond limits/max_speed, "
                                            "max_yaw_rate): the odometry history restarts here", now)
                history.reset()
                history.add_odometry(t, T_odom_base if six else se2)
                return []
        if six:
            self.odometry6.add_odometry(t, T_odom_base)
            return self._odometry_output6(t)
        self.odometry.add_odometry(t, se2)
        if not self.filter.initialized or self.filter.stamp is None or t <= self.filter.stamp:
            return []
        self._advance(t)
        self.odometry_outputs += 1
        track = TrackResult(stamp=t, localization=LocalizationResult(stamp=t), pose=self.filter.pose,
                            covariance=self.filter.covariance)
        return [self._output(track, from_odometry=True)]

    def _odometry_output6(self, t: float) -> List[PoseOutput]:
        """The 6-DOF tracker advanced along the odometry to its message at ``t`` and its pose there,
        as the planar filter's (a pose at the odometry's rate): only while the track may publish
        (:meth:`Tracker6.publishable`: the coasting limits count from the last accepted
        measurement, whatever carries the prediction)."""
        tracker = self.tracker6
        if not tracker.initialized or t <= tracker.stamp:
            return []
        inc = self.odometry6.increment(tracker.stamp, t)
        if inc is None:
            return []
        tracker.predict_increment(t, *inc)
        if not tracker.initialized or not tracker.publishable(t, count=False):
            return []
        self.odometry_outputs += 1
        T = tracker.pose
        track = TrackResult(stamp=t, localization=LocalizationResult(stamp=t), T_map_base=T,
                            pose=geo.se2_from_transform(T), covariance=se2_covariance(tracker.covariance))
        return [self._output(track, from_odometry=True)]

    def _odometry_jump(self, last: float, t: float, pose) -> Optional[Tuple[float, float]]:
        """(distance m, rotation rad) of the odometry's move from its pose at ``last`` to ``pose`` at
        ``t`` when it is beyond ``limits.max_speed`` / ``limits.max_yaw_rate`` (the 6-DOF rotation's
        angle for the 6-DOF tracker) times the stamps' difference plus 2 cm / 2 deg, else None."""
        if self.tracker6 is not None:
            prev6 = self.odometry6.pose_at(last)
            if prev6 is None:
                return None
            D = geo.inverse(prev6) @ pose
            dist, angle = float(np.linalg.norm(D[:3, 3])), geo.rotation_angle(D[:3, :3])
        else:
            prev = self.odometry.pose_at(last)
            if prev is None:
                return None
            d = se2_between(prev, pose)
            dist, angle = float(np.hypot(d[0], d[1])), abs(float(d[2]))
        lim, dt = self.config.limits, t - last
        if dist > lim.max_speed * dt + 0.02 or angle > lim.max_yaw_rate * dt + np.radians(2.0):
            return dist, angle
        return None

    @property
    def _odometry_on(self) -> bool:
        return self.config.motion.odometry and self.odometry.latest_stamp is not None

    def _advance(self, stamp: float) -> None:
        """Predict the filter to ``stamp``: with the odometry increment when the history covers it,
        else with the paper's constant-acceleration model."""
        if self._odometry_on and self.filter.stamp is not None and stamp > self.filter.stamp:
            inc = self.odometry.increment(self.filter.stamp, stamp)
            if inc is not None:
                self.filter.predict_increment(stamp, *inc)
                return
        self.filter.predict(stamp)

    def _predicted_se2(self, stamp: float) -> Tuple[np.ndarray, np.ndarray]:
        """The filter's (x, y, yaw) and 3x3 covariance at ``stamp`` without changing it: along the
        odometry when it covers the interval (also back in time), else the filter's own model."""
        f = self.filter
        if self._odometry_on and f.stamp is not None and stamp != f.stamp:
            inc = self.odometry.increment(f.stamp, stamp)
            if inc is not None:
                return propagate_se2(f.pose, f.covariance, *inc)
        return f.predicted(stamp), f.predicted_covariance(stamp)

    def _motion_model(self, t_ref: float, t_c: float) -> Optional[Tuple[np.ndarray, ...]]:
        """The robot's displacement from ``t_ref`` to ``t_c`` (body frame at ``t_ref``) and its
        covariance, for a free-running camera: odometry when it covers both stamps, else the
        filter's body velocity held constant (covariance ``dt^2`` times the velocity's); None
        before the track starts.

        With the filter's velocity the error is the velocity's, one error for every camera of the
        ring frame: the third element ``dt · L`` (``L L^T`` the velocity's covariance, signed
        ``dt``) tells the estimator so (:data:`localization.MotionModel`), and its covariance
        does not average it away over the cameras (issue 12: ``nees_joint_moving``)."""
        if self._odometry_on:
            inc = self.odometry.increment(t_ref, t_c)
            if inc is not None:
                return inc
        if not self.filter.initialized:
            return None
        dt = float(t_c) - float(t_ref)
        if self._frame_velocity is None:
            # The filter's velocity and its covariance in the body frame, and the factor: the same
            # for every camera of the ring frame (the filter changes only after the frame's pose
            # and marker check; _track clears this at each frame).
            twist = self.filter.body_twist
            c, s = np.cos(self.filter.pose[2]), np.sin(self.filter.pose[2])
            R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])   # map -> body
            V = R @ self.filter.velocity_covariance @ R.T
            self._frame_velocity = (twist, V, psd_factor(V))
        twist, V, F = self._frame_velocity
        return constant_velocity_displacement(twist, dt), dt * dt * V, dt * F

    def on_initial_pose(self, pose, now: float) -> List[PoseOutput]:
        """Restart the track at ``pose`` (4x4 ``T_map_base`` or (x, y, yaw)): rviz's initialpose.

        Raises:
            MeasurementError: a pose that is not finite.
        """
        P = np.asarray(pose, dtype=np.float64)
        try:
            se2 = geo.se2_from_transform(geo.validate_transform(P, "initialpose")) if P.shape == (4, 4) \
                else P.reshape(3)
        except (GeometryError, ValueError) as exc:
            raise MeasurementError(f"initialpose: {exc}") from None
        if not np.all(np.isfinite(se2)):
            raise MeasurementError(f"initialpose: not finite: {se2.tolist()}")
        m = self.config.limits.initial_pose_margin
        x0, y0, x1, y1 = self.extent
        if not (x0 - m <= se2[0] <= x1 + m and y0 - m <= se2[1] <= y1 + m):
            raise MeasurementError(f"initialpose: ({se2[0]:.4g}, {se2[1]:.4g}) lies outside the map: its markers "
                                   f"span x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f} m (+ limits/initial_pose_margin "
                                   f"{m} m)")
        self._tick(now)
        stamp = self._last_stamp if self._last_stamp is not None else float(now)
        self._reset(se2, stamp)
        return []

    def reset(self) -> None:
        """Forget the track: the next measurement initialises it (the ``~reset`` service)."""
        self._reset(None, None)

    def poll(self, now: float) -> List[PoseOutput]:
        """Call periodically: ring frames that timed out, and the prediction while every camera is silent.

        After ``input.silent_after`` s of ``now`` without any ring frame (the assembler emits
        nothing when no camera reports) the filter predicts to ``now`` and the pose goes out with
        its growing covariance (``PoseOutput.predicted_only``), with a throttled warning.
        """
        self._tick(now)
        out = self._process(self.input.poll(now), now)
        if out or self._last_frame_now is None or not self.filter.initialized:
            return out
        blind = now - self._last_frame_now
        if blind < self.config.input.silent_after or self.filter.stamp is None or now <= self.filter.stamp:
            return out  # not silent long enough, or the clock has not moved (a paused bag)
        last_odom = self.odometry.latest_stamp
        if self._odometry_on and last_odom is not None and now - last_odom <= self.config.timing.motion_timeout:
            return out  # odometry predicts and publishes (on_motion)
        track = self._track(RingFrame(stamp=float(now), missing=list(self.input.camera_names)))
        self.warn("blind", f"localizer: no ring frame for {blind:.1f} s (every camera silent): predicting only, "
                           "the covariance grows", now)
        if track.pose is None:
            return out
        self.predicted_only += 1
        return [self._output(track, predicted_only=True)]

    def flush(self, now: float) -> List[PoseOutput]:
        """Every pending ring frame, complete or not (the end of a bag)."""
        return self._process(self.input.poll(now, flush=True), now)

    # --- queries ------------------------------------------------------------------------------

    @property
    def height(self) -> float:
        """z of base_link in the map frame from the last accepted measurement, m."""
        return self._z

    def prediction(self, stamp: float) -> Optional[np.ndarray]:
        """Predicted ``T_map_base`` (4x4) at ``stamp``, or None without a track."""
        if self.tracker6 is not None:
            return self.tracker6.predicted(stamp)
        if not self.filter.initialized:
            return None
        x, y, yaw = self._predicted_se2(stamp)[0] if self._odometry_on else self.filter.predicted(stamp)
        return geo.transform_from_se2(x, y, yaw, self._z)

    def remap_markers(self, marker_ids: Sequence[int]) -> List[Tuple[int, float, str]]:
        """Re-estimate each marker from its recent observations with the others fixed, in the map in
        memory (the ``~remap_marker`` service); returns (id, moved m, "") or (id, nan, why not) each."""
        if self.marker_check is None:
            raise ConfigError("marker_check is disabled: no observations kept to re-map from",
                              key="marker_check.enabled")
        out = []
        for mid in marker_ids:
            try:
                _, moved = self.marker_check.remap(int(mid))
            except MeasurementError as exc:
                out.append((int(mid), float("nan"), str(exc)))
                continue
            self.localizer.forget_marker(int(mid))
            out.append((int(mid), moved, ""))
        return out

    def save_map(self, path: str) -> None:
        """Write the map in memory (with markers re-mapped by :meth:`remap_markers`) to ``path``
        atomically, keeping ``marker_check.backups`` previous versions (the ``~save_map`` service)."""
        self.marker_map.save(path, backups=self.config.marker_check.backups)

    def markers_in_view(self, now: float, window: float) -> set:
        """Ids of the mapped markers used within ``window`` s before ``now``."""
        return {m for m, t in self._in_view.items() if 0.0 <= now - t < window}

    def diagnostics(self, now: float) -> List[StatusReport]:
        """One status per camera and one for the filter (what ``/diagnostics`` shows)."""
        out = []
        silent = set(self.input.silent_cameras(now))
        for name in self.input.camera_names:
            st = self._camera_stats.get(name)
            alive = name not in silent
            rate = st["frames"] / max(now - st["first"], 1e-3) if st else 0.0
            skipped = sum(self.input.skipped[name].values())
            rejected = sum(self.input.rejected[name].values())
            out.append(StatusReport(
                f"aruco_ring localizer: camera {name}", name, alive,
                "alive" if alive else "silent (no detections, camera_info or tf)",
                [("alive", str(alive)), ("rate_hz", f"{rate:.1f}"),
                 ("markers_seen", str(int(st["markers"])) if st else "0"),
                 ("frames_skipped", str(skipped)), ("detections_dropped", str(rejected))]))
        age = None if self.last_update_now is None else now - self.last_update_now
        if age is None:
            ok, message = False, "not initialised (no usable measurement yet)"
        elif age > 2.0:
            ok, message = False, f"no accepted measurement for {age:.1f} s"
        else:
            ok, message = True, "tracking"
        cov = self.filter.covariance if self.filter.initialized else np.full((3, 3), np.nan)
        lat = np.array(self.latency_ms) if self.latency_ms else np.array([np.nan])
        values = [("last_update_age_s", "none" if age is None else f"{age:.2f}"),
                  ("std_x_m", f"{np.sqrt(cov[0, 0]):.4f}"), ("std_y_m", f"{np.sqrt(cov[1, 1]):.4f}"),
                  ("std_yaw_deg", f"{np.degrees(np.sqrt(cov[2, 2])):.3f}"),
                  ("frames", str(self.frames)), ("dropped_stale", str(self.dropped_stale)),
                  ("camera_frames_late", str(self.input.assembler.dropped_late)),
                  ("frames_with_missing_cameras", str(self.frames_missing)),
                  ("predicted_only", str(self.predicted_only)),
                  ("time_jumps", str(self.time_jumps)),
                  ("pauses", str(self.pauses)),
                  ("reinitializations", str(self.gate.reinitializations)),
                  ("latency_ms_median", f"{np.median(lat):.2f}")]
        values += [(f"rejected_{k.replace(' ', '_')}", str(v)) for k, v in sorted(self.rejected_counts.items())]
        if self.marker_check is not None:
            out.append(self._marker_report())
        out.append(StatusReport("aruco_ring localizer: filter", "localizer", ok, message, values))   # last, as before
        return out

    def _marker_report(self) -> StatusReport:
        """The moved-marker check's status: WARN naming each moved marker and how far it moved."""
        mc = self.marker_check
        moved = sorted(mc.moved.values(), key=lambda m: m.marker_id)
        message = ("moved (dropped from the pose): " + ", ".join(f"{m.marker_id} by {100 * m.distance:.1f} cm"
                                                                  for m in moved)) if moved else "no moved marker"
        values = [("moved_markers", " ".join(str(m.marker_id) for m in moved)),
                  ("frames_checked", str(mc.frames_checked)), ("frames_moving", str(mc.frames_moving)),
                  ("declared", str(mc.declarations))]
        values += [(f"marker_{m.marker_id}_moved_cm", f"{100 * m.distance:.1f}") for m in moved]
        values += [(f"marker_{m.marker_id}_displacement_m", " ".join(f"{v:.3f}" for v in m.displacement))
                   for m in moved]
        return StatusReport("aruco_ring localizer: markers", "localizer", not moved, message, values)

    # --- the pipeline -------------------------------------------------------------------------

    def _tick(self, now: float) -> None:
        """The clock policy, at every event, on the node's clock (never on a message's stamp).

        * The clock went back by more than ``filter.time_jump_tolerance`` (a bag loop, a /clock
          reset): the track starts over (``time_jumps``).
        * It moved forward by more than ``timing.max_pause`` since the previous event (the process
          was stopped or starved, the machine suspended, a recording has a gap): the track is not
          extrapolated over the gap, nothing is predicted across it, and the next measurement
          re-initialises the track (``pauses``): no jump from a stale prediction.
        """
        now = float(now)
        last = self._clock
        if last is None or not math.isfinite(now):
            self._clock = now if math.isfinite(now) else last
            return
        if now < last - self.config.filter.time_jump_tolerance:
            self.time_jumps += 1
            self._clock_jumped = True
            self.gate.reset()
            self.filter.reset()
            if self.tracker6 is not None:
                self.tracker6.reset()
            self.odometry.reset()
            self.odometry6.reset()
            logger.warning("localizer: time jumped back from %.3f to %.3f s: filter reset", last, now)
            self._clock = now
            return
        if now - last > self.config.timing.max_pause and (self.filter.initialized or (
                self.tracker6 is not None and self.tracker6.initialized)):
            self.pauses += 1
            logger.warning("localizer: the node's clock moved %.2f s between two events (more than timing/max_pause "
                           "%.2f s: the node was stopped or starved, or the input has a gap); the track restarts "
                           "from the next measurement", now - last, self.config.timing.max_pause)
            self._reset(None, None)
        self._clock = max(last, now)

    def _process(self, frames: List[RingFrame], now: float) -> List[PoseOutput]:
        if not frames:
            return []
        self._last_frame_now = float(now)
        if len(frames) > 1:
            # Never fall behind: a ring frame that a newer one overtook is worth less than the newest.
            self.dropped_stale += len(frames) - 1
            self.warn("stale", f"localizer: dropped {self.dropped_stale} stale ring frames so far ({len(frames) - 1} "
                               f"overtaken at {frames[-1].stamp:.3f} s)", now)
            frames = frames[-1:]
        frame = frames[0]
        age = float(now) - frame.stamp
        max_age = self.config.timing.max_frame_age
        if max_age > 0 and age > max_age:
            self.dropped_stale += 1
            self.warn("stale", f"localizer: dropped {self.dropped_stale} stale ring frames so far (last "
                               f"{age:.2f} s old > timing/max_frame_age {max_age} s)", now)
            return []
        track_stamp = self.filter.stamp if self.tracker6 is None else self.tracker6.stamp
        behind = None if track_stamp is None else track_stamp - frame.stamp
        if -age > self.config.input.max_stamp_ahead or (
                behind is not None and behind > self.config.filter.time_jump_tolerance):
            # Assembled before the clock went back, or later than the track by more than a time
            # jump: a late frame is dropped; only the node's clock going back restarts the track.
            self.dropped_stale += 1
            self.warn("late", f"localizer: dropped {self.dropped_stale} stale ring frames so far (last at "
                              f"{frame.stamp:.3f} s: {-age:+.2f} s from the clock, "
                              f"{0.0 if behind is None else behind:.2f} s behind the track)", now)
            return []
        t0 = time.perf_counter()
        track = self._track(frame)
        self.latency_ms.append(1000.0 * (time.perf_counter() - t0))
        self.frames += 1
        if frame.missing:
            self.frames_missing += 1
        for name, cf in frame.cameras.items():
            st = self._camera_stats.setdefault(name, {"frames": 0, "first": float(now), "markers": 0})
            st["frames"] += 1
            st["markers"] = len(cf.observations)
            st["last"] = float(now)
        for mid in track.localization.marker_ids:
            self._in_view[mid] = float(now)
        decision = track.decision
        if decision is not None and decision.accepted:
            self.last_update_now = float(now)
        elif decision is not None and decision.reason in (REJECTED_JUMP, REJECTED_TILT):
            self.warn("gate", f"localizer: measurement rejected by the gate (jump {decision.distance:.2f} m / "
                              f"{np.degrees(decision.angle):.1f} deg; allowed {decision.allowed_distance:.2f} m / "
                              f"{np.degrees(decision.allowed_angle):.1f} deg)", now)
        elif decision is not None and decision.reason == REJECTED_AMBIGUOUS:
            self.warn("ambiguous", "localizer: measurement not used: ambiguous (a single marker's two poses both fit "
                                   "and nothing in the frame tells them apart)", now)
        # (else the 6-DOF tracker's "pending": a track starts from init_count consistent measurements.)
        if track.pose is None:
            return []
        return [self._output(track)]

    def _speeds(self, now: float) -> Tuple[float, float]:
        """The largest speed and yaw rate of the motion inputs fresh at ``now`` (the node's clock)."""
        fresh = [m for m in self._motion.values() if now - m.stamp <= self.config.timing.motion_timeout]
        return (max((m.speed for m in fresh), default=0.0), max((m.yaw_rate for m in fresh), default=0.0))

    def _reset(self, pose, stamp: Optional[float]) -> None:
        if self.marker_check is not None:
            self.marker_check.reset()
        self.gate.reset()
        self.filter.reset(pose, stamp)
        if self.tracker6 is not None:
            self.tracker6.reset(None if pose is None else geo.transform_from_se2(pose[0], pose[1], pose[2], self._z),
                                stamp if stamp is not None else 0.0)
        if pose is not None:
            self.gate.last_accepted_stamp = float(stamp if stamp is not None else 0.0)
        logger.info("localizer: track reset%s", "" if pose is None else
                    f" at ({pose[0]:.2f}, {pose[1]:.2f}, {np.degrees(pose[2]):.1f} deg)")

    def _track(self, ring_frame: RingFrame) -> TrackResult:
        """Paper Algorithm 1, steps 2-5, on one ring frame."""
        stamp = float(ring_frame.stamp)
        self._last_stamp = stamp
        time_jump = self._clock_jumped   # the clock went back (_tick reset the track and said so)
        self._clock_jumped = False
        if self.filter.check_time(stamp):
            # A stamp far behind the track with the clock steady (a driver that did not use _tick).
            self.gate.reset()
            self.time_jumps += 1
            time_jump = True
            logger.warning("localizer: time jumped back to %.3f s: filter reset", stamp)
        if self.tracker6 is not None:
            return self._track6(ring_frame, stamp, time_jump)
        pred = self.prediction(stamp)
        self._frame_velocity = None   # _motion_model's per-frame part, computed at its first call
        motion = self._motion_model if self.config.motion.compensate_stamps else None
        check = self.marker_check
        loc = self.localizer.process(ring_frame if check is None else check.strip(ring_frame), pred, motion)
        # (pose_distance's translation part, |t_pred - t_loc|, without its rotation angle and inverse)
        if check is not None and loc.ok and not loc.ambiguous and pred is not None and \
                math.sqrt(((pred[:3, 3] - loc.T_map_base[:3, 3]) ** 2).sum()) <= self.config.gate.base_distance:
            # Moved-marker check (marker_check.py) on a measurement near the prediction, before the
            # filter: a marker declared moved now is dropped from this very frame's pose.
            speed, yaw_rate = self._speeds(stamp if self._clock is None else self._clock)
            if self.filter.initialized:
                twist = self.filter.body_twist
                speed, yaw_rate = max(speed, float(np.hypot(twist[0], twist[1]))), max(yaw_rate, abs(float(twist[2])))
            if check.update(ring_frame, loc.T_map_base, self.localizer.ring, stamp, motion, (speed, yaw_rate),
                            known_views=self.localizer.last_views):
                loc = self.localizer.process(check.strip(ring_frame), pred, motion)
            check.warn_moved(stamp if self._clock is None else self._clock)
        for k, v in loc.rejected.items():
            self.rejected_counts[k] = self.rejected_counts.get(k, 0) + v
        out = TrackResult(stamp=stamp, localization=loc, time_jump=time_jump)
        odometry = self._odometry_on and self.filter.initialized
        if odometry and stamp > self.filter.stamp:
            self._advance(stamp)   # along the odometry up to the frame
        t_update = stamp
        if loc.ok:
            z = loc.se2
            cov = loc.covariance_se2
            if odometry and stamp < self.filter.stamp:
                # Odometry moved the filter past the frame (camera latency): the measurement is moved
                # along the odometry to the filter's stamp, with the increment's covariance.
                inc = self.odometry.increment(stamp, self.filter.stamp)
                if inc is not None:
                    z, cov = propagate_se2(z, cov if cov is not None else
                                           self.filter.measurement_covariance(None), *inc)
                    t_update = self.filter.stamp
            speed, yaw_rate = self._speeds(stamp if self._clock is None else self._clock)
            predicted = None if pred is None else geo.se2_from_transform(pred)
            if odometry and predicted is not None:
                predicted = self._predicted_se2(t_update)[0]
            gate_cov = None
            if predicted is not None:
                # Covariance of (z - prediction): the filter's predicted covariance + the measurement's.
                P_pred = self._predicted_se2(t_update)[1] if odometry else self.filter.predicted_covariance(stamp)
                gate_cov = P_pred + self.filter.measurement_covariance(cov)
            # The full rotation goes in too (a flipped pose tilts), and whether the localizer found
            # the measurement ambiguous (then it is not used).
            decision = self.gate.check(z, t_update, predicted, speed, yaw_rate, gate_cov,
                                       rotation=loc.T_map_base[:3, :3], ambiguous=loc.ambiguous)
            out.decision = decision
            if decision.reinitialize:
                if decision.reason != "initialized":
                    logger.warning("localizer: re-initialised after consistent measurements disagreed with the "
                                   "track")
                self.filter.reset(z, t_update, cov)
                self._keep_attitude(loc.T_map_base)
            elif decision.accepted:
                self.filter.update(z, t_update, cov)
                self._keep_attitude(loc.T_map_base)
            else:
                self.rejected_counts["gate"] = self.rejected_counts.get("gate", 0) + 1
                self._advance(stamp)
        else:
            self._advance(stamp)
        if odometry and self.filter.stamp is not None:
            out.stamp = max(out.stamp, self.filter.stamp)   # the pose is the filter's, at its stamp
        if self.filter.initialized:
            out.pose = self.filter.pose
            out.covariance = self.filter.covariance
        self.last_track = out
        return out

    def _track6(self, ring_frame: RingFrame, stamp: float, time_jump: bool) -> TrackResult:
        """:meth:`_track` with the 6-DOF tracker (``filter/model: 6dof``): its own gate and filter."""
        tracker = self.tracker6
        if tracker.stamp is not None and stamp < tracker.stamp - self.config.filter.time_jump_tolerance:
            tracker.reset()
            self.time_jumps += 1
            time_jump = True
            logger.warning("localizer: time jumped back to %.3f s: 6-DOF track reset", stamp)
        odometry = self.config.motion.odometry and tracker.initialized
        if odometry and stamp > tracker.stamp:
            inc = self.odometry6.increment(tracker.stamp, stamp)   # None: the motion model
            if inc is not None:
                tracker.predict_increment(stamp, *inc)
        pred = tracker.predicted(stamp)
        # The odometry moved the track past the frame (camera latency): the prediction at the
        # frame's stamp is the track carried back along the odometry, and the measurement is
        # carried forward to the track's stamp (as the planar filter's, _track).
        ahead = self.odometry6.increment(stamp, tracker.stamp) if odometry and stamp < tracker.stamp else None
        if ahead is not None:
            pred = tracker.pose @ geo.inverse(ahead[0])
        loc = self.localizer.process(ring_frame, pred)
        for k, v in loc.rejected.items():
            self.rejected_counts[k] = self.rejected_counts.get(k, 0) + v
        out = TrackResult(stamp=stamp, localization=loc, time_jump=time_jump)
        if loc.ok:
            T_meas, cov, t_update, alternatives = loc.T_map_base, loc.covariance, stamp, loc.alternatives
            if ahead is not None:
                # The increment's own noise is not added: the track came to its stamp along the same
                # increment, so that noise is in the prediction already and cancels in the innovation
                # (adding it again would count it twice and underweight the measurement).
                T_meas, cov = move_pose(T_meas, cov, ahead[0], np.zeros((6, 6)))
                alternatives = [move_pose(A, None, *ahead)[0] for A in alternatives]
                t_update = tracker.stamp
            out.decision = tracker.update(T_meas, t_update, cov, ambiguous=loc.ambiguous,
                                          markers=len(loc.marker_ids), alternatives=alternatives)
            if out.decision.accepted:
                self._keep_attitude(loc.T_map_base)
            else:
                key = "gate" if out.decision.reason != "pending" else "track_pending"
                self.rejected_counts[key] = self.rejected_counts.get(key, 0) + 1
        else:
            tracker.predict(stamp)
        if odometry and tracker.stamp is not None:
            out.stamp = max(out.stamp, tracker.stamp)   # the pose is the track's, at its stamp
        if tracker.initialized and tracker.publishable(out.stamp):
            T = tracker.pose
            out.T_map_base = T
            out.pose = geo.se2_from_transform(T)
            out.covariance = se2_covariance(tracker.covariance)
        self.last_track = out
        return out

    def _keep_attitude(self, T_map_base: np.ndarray) -> None:
        self._z = float(T_map_base[2, 3])
        roll, pitch, _ = geo.rpy_from_matrix(T_map_base)
        self._roll_pitch = (float(roll), float(pitch))

    def _output(self, track: TrackResult, predicted_only: bool = False, from_odometry: bool = False) -> PoseOutput:
        if track.T_map_base is not None:
            # The 6-DOF tracker: its full pose on ~pose and tf (a handheld rig's roll and pitch are its state).
            tr = self.tracker6
            estimates = {name: e.T_map_base for name, e in track.localization.estimates.items() if e.valid}
            # Covariances over (x, y, z, map-frame rotation vector): for small rotations its
            # components are the roll, pitch and yaw increments of REP-103's layout.
            return PoseOutput(stamp=track.stamp, T_map_base=track.T_map_base, T_map_base_6dof=track.T_map_base,
                              covariance=tr.covariance, twist=tr.body_twist(),
                              twist_covariance=tr.velocity_covariance,
                              camera_estimates=estimates, track=track, predicted_only=predicted_only,
                              from_odometry=from_odometry)
        x, y, yaw = track.pose
        T = geo.transform_from_se2(x, y, yaw, self._z)
        T6 = geo.transform_from_rpy(self._roll_pitch[0], self._roll_pitch[1], yaw, (x, y, self._z))
        # Read only by a ~camera_estimates subscriber: the per-camera estimates are computed then.
        estimates = LazyMapping(lambda out: out.update((name, e.T_map_base) for name, e
                                                       in track.localization.estimates.items() if e.valid))
        return PoseOutput(stamp=track.stamp, T_map_base=T, T_map_base_6dof=T6,
                          covariance=pose_covariance_from_se2(track.covariance),
                          twist=self.filter.body_twist,
                          twist_covariance=pose_covariance_from_se2(self.filter.velocity_covariance),
                          camera_estimates=estimates, track=track, predicted_only=predicted_only,
                          from_odometry=from_odometry)


# --- mapping ---------------------------------------------------------------------------------------

class MappingPipeline(_RingPipeline):
    """Detections (+ camera_info, extrinsics) in, a marker map out: the mapper node and ``build-map``.

    Args:
        config: the mapper's schema (config/mapping.yaml).
        ring: the calibrated ring (the ring file).

    The :class:`MapBuilder` is this object's own (:attr:`builder`): the extrinsics in force reach
    it through :meth:`on_extrinsics`, never from outside.
    """

    def __init__(self, config: MapperConfig, ring: CameraRing):
        self.config = config
        self.warn = ThrottledWarnings(logger.warning, WARN_PERIOD)
        rough = config.calibration.rough
        # Calibrating from rough values: the ring file's extrinsics are the start, never tf's (the
        # mapper publishes the ring's tf itself in that mode).
        self.input = RingInput(ring, replace(config.input, use_tf=False) if rough else config.input, self.warn,
                               label="mapper")
        #: the rough ring (calibration/extrinsics rough), the start of every calibration; None otherwise.
        self.rough_ring: Optional[CameraRing] = ring if rough else None
        #: the last calibration from rough values (:meth:`calibrate`), None before.
        self.calibration: Optional[RingCalibration] = None
        self._calib_frames: List[RingFrame] = []
        self._calib_seen = 0      # frames with markers offered for the calibration
        self._calib_stride = 1    # one in this many of them is kept (doubles at calibration.keep_frames)
        # A surveyed frame: read once here, so a bad anchors file stops the node (or build-map) at
        # start, naming the file and the key.
        anchors = load_anchors(config.map.anchors_file) if config.map.anchors_file else None
        boards = None
        if config.map.boards_file:
            from .importers import tagslam_boards
            boards = tagslam_boards(config.map.boards_file)
            if not len(boards):
                raise ConfigError("no static board or staggered_board body: nothing to use as boards",
                                  path=config.map.boards_file, key="bodies")
        self.builder = MapBuilder(self.input.ring, config.markers.sizes(), method=config.map.method,
                                  reference_marker=config.map.reference, options=config.mapping,
                                  frame_id=config.map.map_frame, anchors=anchors, boards=boards)
        self.frames_missing = 0  # ring frames added without every camera
        self._last_stamp: Optional[float] = None   # stamp of the latest frame the builder placed

    # --- events -----------------------------------------------------------------------------

    def _use_ring(self, ring: CameraRing) -> None:
        self.builder.set_ring(ring)

    def on_detections(self, camera: str, stamp: float, observations: Sequence[MarkerObservation],
                      now: float) -> int:
        """One camera's detections; returns the number of ring frames added to the map."""
        return self._add(self.input.add_detections(camera, stamp, observations, now))

    def poll(self, now: float) -> int:
        """Ring frames that timed out (call periodically); returns how many were added."""
        return self._add(self.input.poll(now))

    def flush(self, now: float) -> int:
        """Every pending ring frame, complete or not (the end of a bag)."""
        return self._add(self.input.poll(now, flush=True))

    def clear(self) -> None:
        """Forget every observation (the ``~clear`` service), and the frames kept for the calibration."""
        self.builder.clear()
        self._calib_frames, self._calib_seen, self._calib_stride = [], 0, 1

    # --- calibration from rough values (calibration/extrinsics rough) ------------------------------------

    def _keep_for_calibration(self, frame: RingFrame) -> None:
        if self.rough_ring is None or frame.observation_count() == 0:
            return
        self._calib_seen += 1
        if (self._calib_seen - 1) % self._calib_stride:
            return
        self._calib_frames.append(frame)
        if len(self._calib_frames) >= self.config.calibration.keep_frames:
            # Bounded memory, still spread evenly over the whole run.
            self._calib_frames = self._calib_frames[::2]
            self._calib_stride *= 2

    @property
    def calibration_stamps(self) -> List[float]:
        """Stamps of the frames kept for the calibration (where the node looks up the odometry)."""
        return [f.stamp for f in self._calib_frames]

    def calibrate(self, odometry: Optional[Sequence[Tuple[float, np.ndarray]]] = None) -> RingCalibration:
        """Calibrate the ring from the rough values and the frames kept so far
        (:func:`ring_calibration.calibrate_ring`; ``odometry`` [(stamp, T_odom_base)] gives base_link's
        heading); from now on the map is built with the calibrated extrinsics (those of the frames
        already added included).

        Raises:
            ConfigError: calibration/extrinsics is not rough. MeasurementError: too few usable frames.
        """
        if self.rough_ring is None:
            raise ConfigError("the mapper calibrates the ring only from rough values (calibration/extrinsics: rough)",
                              key="calibration.extrinsics")
        cp = self.config.calibration
        cal = calibrate_ring(self._calib_frames, self.rough_ring, self.config.markers.sizes(),
                             odometry=odometry or None, options=CalibrationOptions(max_frames=cp.max_frames))
        for name in self.input.camera_names:
            self.input.set_extrinsics(name, cal.ring[name].T_base_cam)
        self.builder.recalibrate(self.input.ring)
        self.calibration = cal
        return cal

    @property
    def odometry_topic(self) -> str:
        """``mapping.odometry.topic``: the nav_msgs/Odometry whose poses link the stations ("": none)."""
        return self.config.mapping.odometry.topic

    def on_odometry(self, stamp: float, T_odom_body: np.ndarray) -> bool:
        """One odometry pose (the odometry body in its odom frame, ``mapping.odometry``): kept to link
        consecutive stations in the bundle adjustment. False when it is not a rigid transform."""
        return self.builder.add_odometry(stamp, T_odom_body)

    # --- the map ------------------------------------------------------------------------------

    def build(self, method: Optional[str] = None) -> MarkerMap:
        """The map (``paper`` or ``refined``; default ``map.method``)."""
        return self.builder.build(method)

    def save(self, path: str) -> MarkerMap:
        """Build with ``map.method`` and write ``path`` atomically, keeping ``map.backups`` previous
        versions (:meth:`MapBuilder.save_map`)."""
        return self.builder.save_map(path, backups=self.config.map.backups)

    @property
    def version(self) -> int:
        """Changes whenever an observation is added (or the map cleared)."""
        return self.builder.version

    @property
    def frames(self) -> int:
        return self.builder.frames

    @property
    def station_count(self) -> int:
        """Robot placements found so far."""
        return self.builder.station_count

    @property
    def last_ba(self):
        """The last bundle adjustment's result (:class:`bundle_adjustment.BAResult`), or None."""
        return self.builder.last_ba

    def summary(self) -> dict:
        return self.builder.summary()

    def format_summary(self) -> str:
        if not self.builder.frames:
            return "no ring frame yet"
        if self.rough_ring is not None and self.calibration is None:
            # Not the map's summary: through rough extrinsics it is wrong and costs an initialisation.
            text = (f"calibrating the ring from rough values: {self.builder.frames} ring frames, "
                    f"{len(self._calib_frames)} kept for the calibration; the map after ~save_map or ~calibrate_ring")
        else:
            text = self.builder.format_summary()
        if self.frames_missing:
            text += f"; {self.frames_missing} ring frames without every camera ({self.input.incomplete_reasons()})"
        return text

    def silent_cameras(self, now: float) -> List[str]:
        return self.input.silent_cameras(now)

    def format_saved(self, m: MarkerMap, path: str) -> str:
        """What ``~save_map`` answers (and logs) after ``m`` was written to ``path``: a loud warning
        first when a detected marker is not in the map (:meth:`MapBuilder.format_unmapped`)."""
        s = self.summary()
        frame = f"map frame on marker {m.reference_marker}"
        if m.anchors is not None:
            res = [p for p in m.anchors["points"] if "residual" in p]
            worst = max(res, key=lambda p: p["residual_sigmas"]) if res else None
            frame = f"surveyed frame ({len(res)} anchors of {m.anchors['source']}"
            if worst is not None:
                frame += (f"; largest residual marker {worst['marker']}: "
                          f"{1000 * float(np.linalg.norm(worst['residual'])):.1f} mm")
            frame += ")"
        elif s["reference_marker"] not in (None, m.reference_marker):
            frame += (f" (the best-determined heading after the adjustment; chaining started from marker "
                      f"{s['reference_marker']}, the paper's rule)")
        obs = ", ".join(f"{e.marker_id}:{e.observations}" for e in m)
        text = (f"saved {len(m)} markers ({m.method}) to {path}; {frame}; {s['frames']} frames, "
                f"{s['linked_stations']}/{s['stations']} stations; observations per marker {{{obs}}}")
        if self.frames_missing:
            text += f"; {self.frames_missing} ring frames without every camera ({self.input.incomplete_reasons()})"
        ba = self.last_ba if m.method == "refined" else None
        if ba is not None:
            text += f"; bundle adjustment RMS {ba.rms_px_before:.2f} -> {ba.rms_px_after:.2f} px in {ba.seconds:.1f} s"
        warning = self.builder.format_unmapped(m)
        return f"{warning}. {text}" if warning else text

    def robot_pose(self, m: MarkerMap) -> Optional[Tuple[float, np.ndarray]]:
        """``(stamp, T_map_base)`` of the robot at the latest frame's station in ``m``'s frame, or None
        (:meth:`MapBuilder.station_pose`): what the mapper puts on tf, so that the robot, its ring and
        its laser appear in the map while mapping."""
        st = self.builder.last_station
        if st is None or self._last_stamp is None:
            return None
        T = self.builder.station_pose(st, m)
        return None if T is None else (self._last_stamp, T)

    def _add(self, frames: List[RingFrame]) -> int:
        for f in frames:
            self.frames_missing += bool(f.missing)
            self._keep_for_calibration(f)
            if self.builder.add_frame(f) >= 0:
                self._last_stamp = f.stamp
        return len(frames)


def ring_file_beside(map_file: str) -> str:
    """Where the mapper writes the ring it calibrated from rough values by default: beside the map,
    ``<map file without .yaml>_ring.yaml``."""
    root, ext = os.path.splitext(map_file)
    return f"{root if ext in ('.yaml', '.yml') else map_file}_ring.yaml"


# --- helpers for in-process drivers (benchmarks, tests, the demo's report) ---------------------------

def feed_ring_frame(pipeline, frame: RingFrame, now: Optional[float] = None, flush: bool = True):
    """Every camera of ``frame`` through ``pipeline.on_detections`` (at ``now``, default the stamp).

    Returns what the pipeline returned (a list of :class:`PoseOutput` for localization, a count for
    mapping). With ``flush``, a ring frame left incomplete (a camera the frame lacks) goes out too.
    """
    t = frame.stamp if now is None else now
    out: list = []
    added = 0
    for name, cf in frame.cameras.items():
        r = pipeline.on_detections(name, cf.stamp, cf.observations, t)
        if isinstance(r, list):
            out += r
        else:
            added += r
    if flush:
        r = pipeline.flush(t)
        if isinstance(r, list):
            out += r
        else:
            added += r
    return out if isinstance(pipeline, LocalizationPipeline) else added


__all__ = ["LocalizationPipeline", "MappingPipeline", "PoseOutput", "TrackResult", "StatusReport", "RingInput",
           "feed_ring_frame", "resolve_camera_names", "pose_covariance_from_se2", "SKIP_NO_CAMERA_INFO",
           "SKIP_NO_EXTRINSICS", "SKIP_BAD_STAMP", "MOTION_SOURCES"]
