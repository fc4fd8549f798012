"""Detections and ring frames: what the cameras saw at one instant, and how it is grouped.

* :class:`MarkerObservation` — one detected marker: id and its 4 raw-pixel corners (aruco_detect order).
* :class:`CameraFrame` — one camera's detections at one stamp (an empty list means "alive, saw nothing").
* :class:`RingFrame` — the ring's cameras grouped by stamp; cameras that did not report are listed.
* :class:`RingFrameAssembler` — groups :class:`CameraFrame` s by stamp within a slop. A camera that
  stops publishing never stalls the others: a group goes out when every camera has reported or
  when it has waited ``timeout`` seconds (of the caller's clock), whichever comes first.
* :func:`sanitize_observations` — drops what must never reach the estimators (NaN corners,
  degenerate quads, duplicate ids in one image, ignored ids) and says why. The pipelines
  (:mod:`pipeline`) call it once, where detections enter; the estimators rely on it.

These types are shared by the simulator, the detector, the mapper and the localizer.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Collection, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .camera import CameraModel
from .markers import quads_ok

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
        max_pending: at most this many incomplete groups are kept; older ones are flushed. None
            (the default): enough for ``timeout`` seconds of a 50 Hz ring, at least 8. A fixed 8
            flushed frames whenever one camera's callback lagged the others by 8 frames (0.8 s
            at 10 Hz, seen on a loaded machine) although the timeout allowed it to catch up.
        silence: a camera that has sent nothing for this long (s) is not waited for: a group
            is complete once every camera heard from within ``silence`` has reported. So a
            dead camera costs one ``timeout`` per frame only until it is found silent, not for ever.
            ``None`` always waits for every camera (up to ``timeout``).
        late_by_clock: the caller's clock is the truth (the localizer's): a frame stamped more than
            1 s before the last ring frame counts as a time jump (start over) only when its stamp is
            recent by the caller's clock too (the clock went back with it); otherwise it is late
            and dropped. False (the mapper): stamps alone decide, so a bag replayed in a loop
            without its clock still maps.

    Usage: call :meth:`add` for every camera frame and :meth:`poll` periodically; both return
    the ring frames that are ready, oldest first.
    """

    def __init__(self, cameras: Sequence[str], slop: float = 0.03, timeout: float = 0.25, max_pending: Optional[int] = None,
                 silence: Optional[float] = 1.0, late_by_clock: bool = False):
        if not cameras:
            raise ValueError("RingFrameAssembler needs at least one camera name")
        if slop < 0 or timeout <= 0:
            raise ValueError(f"slop must be >= 0 and timeout > 0, got slop={slop}, timeout={timeout}")
        self.cameras = list(cameras)
        self.slop = float(slop)
        self.timeout = float(timeout)
        self.max_pending = max(8, int(np.ceil(50.0 * self.timeout))) if max_pending is None else int(max_pending)
        self.silence = silence
        self.late_by_clock = bool(late_by_clock)
        self._first_seen: Optional[float] = None
        self._pending: List[Tuple[float, RingFrame]] = []  # (arrival time, frame), stamp order
        self._last_emitted = -np.inf
        self.last_seen: Dict[str, float] = {}   # camera -> caller's clock at its last frame
        self.dropped_late = 0
        self.time_jumps = 0
        #: Ring frames that went out without every camera, by reason: ``timeout`` (waited
        #: ``timeout`` s), ``silent`` (the missing cameras were silent for ``silence`` s),
        #: ``overtaken`` (a newer frame completed before it, or more than ``max_pending`` waited).
        self.incomplete: Dict[str, int] = {"timeout": 0, "silent": 0, "overtaken": 0}

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
        if frame.stamp < self._last_emitted - 1.0 and not (self.late_by_clock and now - frame.stamp > 1.0):
            # Time went backwards by more than a second (a bag loop, a clock reset): start over.
            # With late_by_clock, a stamp that is old by the caller's clock too is a late message,
            # not a jump (dropped below): one lagging camera must not reset everybody's frames.
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
        for arrived, g in self._pending[: ready_upto + 1]:
            g.missing = [c for c in self.cameras if c not in g.cameras]
            if g.missing:
                # Why it went out incomplete (counted for the nodes' summaries and diagnostics).
                if now - arrived >= self.timeout:
                    self.incomplete["timeout"] += 1
                elif awaited.issubset(g.cameras):
                    self.incomplete["silent"] += 1
                else:
                    self.incomplete["overtaken"] += 1
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

    Drops: ids in ``ignore``; negative ids; corners that are not a finite (4, 2) array; degenerate quads
    (non-convex, self-intersecting, smaller than ``min_area_px``); corners far outside the image
    when the size is known (more than one image size away); and every detection of an id that
    appears more than once in the same image (which one is real cannot be told).

    Returns:
        (kept observations, counts of dropped ones by reason).
    """
    reasons: Dict[str, int] = {}

    def drop(reason: str, n: int = 1) -> None:
        if n:
            reasons[reason] = reasons.get(reason, 0) + n

    candidates: List[MarkerObservation] = []
    arrays: List[np.ndarray] = []
    for obs in observations:
        if obs.marker_id in ignore:
            drop("ignored")
            continue
        if obs.marker_id < 0:
            drop("negative id")   # no dictionary has one: a corrupt message
            continue
        c = np.asarray(obs.corners, dtype=np.float64)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            drop("non-finite")
            continue
        candidates.append(obs if c is obs.corners else MarkerObservation(int(obs.marker_id), c))
        arrays.append(c)
    if not candidates:
        return [], reasons
    q = np.stack(arrays)
    ok = np.ones(len(candidates), dtype=bool)
    if width and height:
        size = np.array([width, height], dtype=np.float64)
        ok = (np.abs(q - 0.5 * size) <= 1.5 * size).all(axis=(1, 2))
        drop("outside image", int(np.count_nonzero(~ok)))
    good = quads_ok(q, min_area_px)
    drop("degenerate", int(np.count_nonzero(ok & ~good)))
    kept = [o for o, k in zip(candidates, ok & good) if k]
    counts = Counter(o.marker_id for o in kept)
    dups = {i for i, n in counts.items() if n > 1}
    if dups:
        reasons["duplicate id"] = sum(counts[i] for i in dups)
        kept = [o for o in kept if o.marker_id not in dups]
    return kept, reasons
