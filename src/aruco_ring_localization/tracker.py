"""The whole localization pipeline without ROS: localizer -> gate -> Kalman filter.

:class:`RingTracker` is what the ``localizer`` node, the ``aruco_ring localize`` command and the
benchmarks run for every ring frame (paper Algorithm 1, steps 2-5):

1. a time jump backwards (bag loop) resets the filter and the gate;
2. the filter's prediction for the frame's stamp seeds :class:`RingLocalizer` (single-marker
   ambiguities, the joint estimator's start);
3. the fused measurement goes through :class:`MotionGate` with the latest motion command /
   odometry speed, its full rotation (a flipped pose tilts) and whether the localizer found it
   ambiguous (then it is not used);
4. accepted: filter update with the estimator's covariance; re-initialisation: filter reset at
   the measurement; rejected or nothing seen: predict only.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np

from . import geometry as geo
from .detections import RingFrame
from .gating import GateDecision, GateParams, MotionGate
from .kalman import FilterParams, PoseFilter
from .localization import LocalizationParams, LocalizationResult, RingLocalizer
from .marker_map import MarkerMap
from .ring import CameraRing

logger = logging.getLogger(__name__)


@dataclass
class TrackResult:
    """One ring frame through the pipeline.

    Attributes:
        stamp: s. localization: the per-frame result. decision: the gate's (None if no pose).
        pose: filtered (x, y, yaw), or None before the first measurement.
        covariance: 3x3 filter covariance of (x, y, yaw), or None.
        time_jump: the filter was reset because time went backwards.
    """

    stamp: float
    localization: LocalizationResult
    decision: Optional[GateDecision] = None
    pose: Optional[np.ndarray] = None
    covariance: Optional[np.ndarray] = None
    time_jump: bool = False


@dataclass
class _Motion:
    speed: float = 0.0
    yaw_rate: float = 0.0
    stamp: float = -np.inf


class RingTracker:
    """Localizer + gate + filter, fed ring frames and motion commands.

    Args:
        ring, marker_map: as :class:`RingLocalizer`.
        localization, gate, filter_params: the three stages' parameters.
        motion_timeout: a motion command/odometry twist older than this (s) counts as zero.
    """

    def __init__(self, ring: CameraRing, marker_map: MarkerMap, localization: Optional[LocalizationParams] = None,
                 gate: Optional[GateParams] = None, filter_params: Optional[FilterParams] = None,
                 motion_timeout: float = 0.5):
        self.localizer = RingLocalizer(ring, marker_map, localization)
        self.gate = MotionGate(gate)
        self.filter = PoseFilter(filter_params)
        self.motion_timeout = float(motion_timeout)
        self._motion: Dict[str, _Motion] = {}
        self._z = 0.0  # height of base_link in the map, from the last measurement
        self.time_jumps = 0
        self.rejected_counts: Dict[str, int] = {}

    @property
    def height(self) -> float:
        """z of base_link in the map frame from the last accepted measurement, m."""
        return self._z

    def set_motion(self, source: str, speed: float, yaw_rate: float, stamp: float) -> None:
        """Latest motion from ``source`` (``cmd_vel`` or ``odom``): |linear| m/s, yaw rate rad/s."""
        self._motion[source] = _Motion(abs(float(speed)), abs(float(yaw_rate)), float(stamp))

    def _speeds(self, stamp: float):
        fresh = [m for m in self._motion.values() if stamp - m.stamp <= self.motion_timeout]
        return (max((m.speed for m in fresh), default=0.0), max((m.yaw_rate for m in fresh), default=0.0))

    def reset(self, pose=None, stamp: Optional[float] = None) -> None:
        """Forget the track; with ``pose`` (x, y, yaw) restart there (rviz initialpose)."""
        self.gate.reset()
        self.filter.reset(pose, stamp)
        if pose is not None:
            self.gate.last_accepted_stamp = float(stamp if stamp is not None else 0.0)
        logger.info("tracker reset%s", "" if pose is None else f" at ({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f})")

    def prediction(self, stamp: float) -> Optional[np.ndarray]:
        """Predicted T_map_base (4x4) at ``stamp``, or None without a track."""
        if not self.filter.initialized:
            return None
        x, y, yaw = self.filter.predicted(stamp)
        return geo.transform_from_se2(x, y, yaw, self._z)

    def process(self, ring_frame: RingFrame) -> TrackResult:
        stamp = float(ring_frame.stamp)
        time_jump = self.filter.check_time(stamp)
        if time_jump:
            self.gate.reset()
            self.time_jumps += 1
        pred = self.prediction(stamp)
        loc = self.localizer.process(ring_frame, pred)
        for k, v in loc.rejected.items():
            self.rejected_counts[k] = self.rejected_counts.get(k, 0) + v
        out = TrackResult(stamp=stamp, localization=loc, time_jump=time_jump)
        if loc.ok:
            z = loc.se2
            cov = loc.covariance_se2
            speed, yaw_rate = self._speeds(stamp)
            predicted = None if pred is None else geo.se2_from_transform(pred)
            gate_cov = None
            if predicted is not None:
                # Covariance of (z - prediction): the filter's predicted covariance + the measurement's.
                gate_cov = self.filter.predicted_covariance(stamp) + self.filter.measurement_covariance(cov)
            decision = self.gate.check(z, stamp, predicted, speed, yaw_rate, gate_cov, rotation=loc.T_map_base[:3, :3],
                                       ambiguous=loc.ambiguous)
            out.decision = decision
            if decision.reinitialize:
                self.filter.reset(z, stamp, cov)
                self._z = float(loc.T_map_base[2, 3])
            elif decision.accepted:
                self.filter.update(z, stamp, cov)
                self._z = float(loc.T_map_base[2, 3])
            else:
                self.rejected_counts["gate"] = self.rejected_counts.get("gate", 0) + 1
                self.filter.predict(stamp)
        else:
            self.filter.predict(stamp)
        if self.filter.initialized:
            out.pose = self.filter.pose
            out.covariance = self.filter.covariance
        return out
