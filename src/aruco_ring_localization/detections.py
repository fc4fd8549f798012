"""Detections and ring frames: what the cameras saw at one instant, and how it is grouped.

* :class:`MarkerObservation` — one detected marker: id and its 4 raw-pixel corners (aruco_detect order).
* :class:`CameraFrame` — one camera's detections at one stamp (an empty list means "alive, saw nothing").
* :class:`RingFrame` — the ring's cameras grouped by stamp; cameras that did not report are listed.
* :class:`RingFrameAssembler` — groups :class:`CameraFrame` s by stamp within a slop. A camera that
  stops publishing never stalls the others: a group goes out when every camera has reported or
  when it has waited ``timeout`` seconds (of the caller's clock), whichever comes first.
* :func:`sanitize_observations` — drops what must never reach the estimators (NaN corners,
  degenerate quads, duplicate ids in one image, ignored ids) and says why.

* :class:`RingInputCore` — the calibration in force (camera_info, extrinsics) and the way in:
  each camera's detections are checked (intrinsics and extrinsics known), sanitized once and
  fed to the assembler.

These types are shared by the simulator, the detector, the mapper and the localizer.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Collection, Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .camera import CameraModel
from .markers import quad_is_degenerate
from .ring import CameraRing

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MarkerObservation:
    """One marker detected in one image.

    Attributes:
        marker_id: ArUco id.
        corners: (4, 2) raw (distorted) pixel coordinates, order 0 top-left, 1 top-right,
            2 bottom-right, 3 bottom-left of the printed marker.
    """

    marker_id: int
    corners: np.ndarray


@dataclass
class CameraFrame:
    """Detections of one camera at one instant.

    Attributes:
        camera: ring camera name (``cam0``).
        stamp: image time, seconds.
        observations: detected markers (may be empty: the camera is alive but saw none).
        model: intrinsics in force for this image (from camera_info), or None to use the ring's.
    """

    camera: str
    stamp: float
    observations: List[MarkerObservation] = field(default_factory=list)
    model: Optional[CameraModel] = None


@dataclass
class RingFrame:
    """Every camera's detections at one instant.

    Attributes:
        stamp: the group's time, seconds (the earliest member's stamp).
        cameras: camera name -> its frame, for the cameras that reported.
        missing: cameras that did not report within the timeout.
    """

    stamp: float
    cameras: Dict[str, CameraFrame] = field(default_factory=dict)
    missing: List[str] = field(default_factory=list)

    def observation_count(self) -> int:
        return sum(len(f.observations) for f in self.cameras.values())


class RingFrameAssembler:
    """Group per-camera frames into ring frames by stamp.

    Args:
        cameras: the names of the cameras expected in each frame.
        slop: frames whose stamps differ by at most this (s) belong to one ring frame.
        timeout: a group that is still incomplete this long (s, caller's clock) after its first
            member arrived goes out without the missing cameras.
        max_pending: at most this many incomplete groups are kept; older ones are flushed.
        silence: a camera that has sent nothing for this long (s) is not waited for: a group
            is complete once every camera heard from within ``silence`` has reported. So a
            dead camera costs one ``timeout`` per frame only until it is found silent, not for ever.
            ``None`` always waits for every camera (up to ``timeout``).

    Usage: call :meth:`add` for every camera frame and :meth:`poll` periodically; both return
    the ring frames that are ready, oldest first.
    """

    def __init__(self, cameras: Sequence[str], slop: float = 0.03, timeout: float = 0.25, max_pending: int = 8,
                 silence: Optional[float] = 1.0):
        if not cameras:
            raise ValueError("RingFrameAssembler needs at least one camera name")
        if slop < 0 or timeout <= 0:
            raise ValueError(f"slop must be >= 0 and timeout > 0, got slop={slop}, timeout={timeout}")
        self.cameras = list(cameras)
        self.slop = float(slop)
        self.timeout = float(timeout)
        self.max_pending = int(max_pending)
        self.silence = silence
        self._first_seen: Optional[float] = None
        self._pending: List[Tuple[float, RingFrame]] = []  # (arrival time, frame), stamp order
        self._last_emitted = -np.inf
        self.last_seen: Dict[str, float] = {}   # camera -> caller's clock at its last frame
        self.dropped_late = 0
        self.time_jumps = 0

    def reset(self) -> None:
        self._pending.clear()
        self._last_emitted = -np.inf

    def add(self, frame: CameraFrame, now: float) -> List[RingFrame]:
        """Take one camera's frame (``now`` is the caller's clock, s); return finished ring frames."""
        if frame.camera not in self.cameras:
            logger.debug("ignoring frame from unknown camera %s", frame.camera)
            return []
        if self.silence is not None and (not self.last_seen or max(self.last_seen.values()) < now - self.silence):
            # Start-up, or every camera was silent: wait for all of them again while they come back.
            self._first_seen = now
        self.last_seen[frame.camera] = now
        if frame.stamp < self._last_emitted - 1.0:
            # Time went backwards by more than a second (a bag loop, a clock reset): start over.
            self.time_jumps += 1
            logger.warning("time jumped back from %.3f to %.3f s; resetting frame assembly",
                           self._last_emitted, frame.stamp)
            self.reset()
        group = None
        for _, g in self._pending:
            if abs(g.stamp - frame.stamp) <= self.slop and frame.camera not in g.cameras:
                group = g
                break
        if group is None:
            if frame.stamp <= self._last_emitted + self.slop:
                # It belongs to a ring frame that already went out (or is older still): a frame
                # of its own would repeat that stamp with one camera, so drop it.
                self.dropped_late += 1
                return self.poll(now)
            group = RingFrame(stamp=frame.stamp)
            self._pending.append((now, group))
            self._pending.sort(key=lambda item: item[1].stamp)
        group.cameras[frame.camera] = frame
        group.stamp = min(group.stamp, frame.stamp)
        return self.poll(now)

    def poll(self, now: float) -> List[RingFrame]:
        """Return the groups that are complete or timed out, and every older group before them."""
        ready_upto = -1
        awaited = self._awaited(now)
        for i, (arrived, g) in enumerate(self._pending):
            if awaited.issubset(g.cameras) or now - arrived >= self.timeout:
                ready_upto = i
        overflow = len(self._pending) - self.max_pending
        ready_upto = max(ready_upto, overflow - 1)
        out = []
        for _, g in self._pending[: ready_upto + 1]:
            g.missing = [c for c in self.cameras if c not in g.cameras]
            out.append(g)
            self._last_emitted = max(self._last_emitted, g.stamp)
        del self._pending[: ready_upto + 1]
        return out

    def _awaited(self, now: float) -> set:
        """The cameras a group waits for: all, less those silent for ``silence`` seconds.

        For ``silence`` seconds after start-up, or after every camera was silent, all cameras are
        awaited: they come up one by one, and the first frame must not go out with one camera.
        """
        if self.silence is None or (self._first_seen is not None and now - self._first_seen < self.silence):
            return set(self.cameras)
        return {c for c in self.cameras if now - self.last_seen.get(c, -np.inf) <= self.silence}

    def silent_cameras(self, now: float, silence: float) -> List[str]:
        """Cameras that have sent nothing for ``silence`` seconds (or never)."""
        return [c for c in self.cameras if now - self.last_seen.get(c, -np.inf) > silence]


def sanitize_observations(observations: Sequence[MarkerObservation], ignore: Collection[int] = (),
                          width: Optional[int] = None, height: Optional[int] = None,
                          min_area_px: float = 4.0) -> Tuple[List[MarkerObservation], Dict[str, int]]:
    """Keep only usable detections.

    Drops: ids in ``ignore``; corners that are not a finite (4, 2) array; degenerate quads
    (non-convex, self-intersecting, smaller than ``min_area_px``); corners far outside the image
    when the size is known (more than one image size away); and every detection of an id that
    appears more than once in the same image (which one is real cannot be told).

    Returns:
        (kept observations, counts of dropped ones by reason).
    """
    reasons: Dict[str, int] = {}
    kept: List[MarkerObservation] = []

    def drop(reason: str) -> None:
        reasons[reason] = reasons.get(reason, 0) + 1

    for obs in observations:
        if obs.marker_id in ignore:
            drop("ignored")
            continue
        c = np.asarray(obs.corners, dtype=np.float64)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            drop("non-finite")
            continue
        if width and height and (np.any(np.abs(c[:, 0] - width / 2) > 1.5 * width)
                                 or np.any(np.abs(c[:, 1] - height / 2) > 1.5 * height)):
            drop("outside image")
            continue
        if quad_is_degenerate(c, min_area_px):
            drop("degenerate")
            continue
        kept.append(obs if c is obs.corners else MarkerObservation(int(obs.marker_id), c))
    counts = Counter(o.marker_id for o in kept)
    dups = {i for i, n in counts.items() if n > 1}
    if dups:
        reasons["duplicate id"] = sum(counts[i] for i in dups)
        kept = [o for o in kept if o.marker_id not in dups]
    return kept, reasons


# --- the way in: calibration in force, sanitizing, assembly -----------------------------------


#: Reasons a whole camera frame is skipped (keys of :attr:`RingInputCore.skipped`).
SKIP_NO_CAMERA_INFO = "no camera_info"
SKIP_NO_EXTRINSICS = "no extrinsics"


class RingInputCore:
    """Assemble ring frames from per-camera detections.

    Args:
        ring: the calibrated ring (names, frames, fallback intrinsics and extrinsics).
        camera_names: ring camera names to use (default: all of the ring's).
        slop: stamps within this (s) belong to one ring frame.
        timeout: an incomplete group goes out this long (s, caller's clock) after its first member.
        ignore_ids: marker ids never passed on.
        camera_info_fallback: use the ring file's intrinsics while no camera_info has arrived.
        extrinsics_from_ring: use the ring file's extrinsics instead of waiting for
            :meth:`set_extrinsics`.
    """

    def __init__(self, ring: CameraRing, camera_names: Optional[Sequence[str]] = None, slop: float = 0.03,
                 timeout: float = 0.25, ignore_ids: Collection[int] = (), camera_info_fallback: bool = False,
                 extrinsics_from_ring: bool = False):
        names = list(camera_names) if camera_names else ring.names
        unknown = [n for n in names if n not in ring.names]
        if unknown:
            raise ValueError(f"cameras {unknown} are not in the ring (known: {ring.names})")
        self.calibrated_ring = ring
        self.camera_names = names
        self.ignore_ids = frozenset(int(i) for i in ignore_ids)
        self.camera_info_fallback = bool(camera_info_fallback)
        self.extrinsics_from_ring = bool(extrinsics_from_ring)
        self.assembler = RingFrameAssembler(names, slop=slop, timeout=timeout)
        self._models: Dict[str, CameraModel] = {}
        self._extrinsics: Dict[str, np.ndarray] = (
            {n: ring[n].T_base_cam for n in names} if extrinsics_from_ring else {})
        self._ring = ring
        #: camera -> {reason: count} of detections dropped by sanitize_observations.
        self.rejected: Dict[str, Dict[str, int]] = {n: {} for n in names}
        #: camera -> {reason: count} of whole camera frames skipped (no camera_info / no extrinsics).
        self.skipped: Dict[str, Dict[str, int]] = {n: {} for n in names}
        self.frames_in = 0
        self.ring_frames_out = 0

    # --- calibration in force ---------------------------------------------------------------

    def set_camera_model(self, camera: str, model: CameraModel) -> None:
        """The intrinsics from this camera's latest camera_info."""
        self._models[camera] = model

    def camera_model(self, camera: str) -> Optional[CameraModel]:
        """Intrinsics in force for ``camera`` (camera_info, or the ring's with the fallback), or None."""
        model = self._models.get(camera)
        if model is None and self.camera_info_fallback:
            model = self.calibrated_ring[camera].model
        return model

    def set_extrinsics(self, camera: str, T_base_cam: np.ndarray) -> None:
        """``T_base_cam`` (4x4) of ``camera`` (from tf); updates :attr:`ring`."""
        T = geo.validate_transform(T_base_cam, f"extrinsics of {camera}")
        self._extrinsics[camera] = T
        self._ring = self.calibrated_ring.with_extrinsics(self._extrinsics)

    def has_extrinsics(self, camera: str) -> bool:
        return camera in self._extrinsics

    @property
    def ring(self) -> CameraRing:
        """The ring with the extrinsics in force (tf's where known, the file's for the others)."""
        return self._ring

    # --- data -------------------------------------------------------------------------------

    def add_detections(self, camera: str, stamp: float, observations: Sequence[MarkerObservation],
                       now: float) -> Tuple[List[RingFrame], Optional[str], Dict[str, int]]:
        """Take one camera's detections at ``stamp`` (s); ``now`` is the caller's clock (s).

        Returns:
            (ring frames ready to go out, the reason the camera frame was skipped or None,
            counts of the detections dropped in this frame by reason).
        """
        self.frames_in += 1
        if camera not in self.skipped:
            return self.poll(now), f"unknown camera {camera}", {}
        model = self.camera_model(camera)
        reason = None
        if model is None:
            reason = SKIP_NO_CAMERA_INFO
        elif camera not in self._extrinsics:
            reason = SKIP_NO_EXTRINSICS
        if reason is not None:
            self.skipped[camera][reason] = self.skipped[camera].get(reason, 0) + 1
            return self.poll(now), reason, {}
        kept, dropped = sanitize_observations(observations, self.ignore_ids, model.width, model.height)
        for k, v in dropped.items():
            self.rejected[camera][k] = self.rejected[camera].get(k, 0) + v
        out = self.assembler.add(CameraFrame(camera, float(stamp), kept, model), now)
        self.ring_frames_out += len(out)
        return out, None, dropped

    def poll(self, now: float) -> List[RingFrame]:
        """Ring frames whose timeout has expired (call periodically)."""
        out = self.assembler.poll(now)
        self.ring_frames_out += len(out)
        return out

    def silent_cameras(self, now: float, silence: float = 1.0) -> List[str]:
        """Cameras from which nothing usable has arrived for ``silence`` s (or ever)."""
        return self.assembler.silent_cameras(now, silence)
