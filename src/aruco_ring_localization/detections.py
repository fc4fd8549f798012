"""Detections and ring frames: what the cameras saw at one instant, and how it is grouped.

* :class:`MarkerObservation` — one detected marker: id and its 4 raw-pixel corners (aruco_detect order).
* :class:`CameraFrame` — one camera's detections at one stamp (an empty list means "alive, saw nothing").
* :class:`RingFrame` — the ring's cameras grouped by stamp; cameras that did not report are listed.
* :class:`RingFrameAssembler` — groups :class:`CameraFrame` s by stamp: one frame period measured
  from the stamps (``slop: auto``, synchronized or free-running cameras) or within a fixed slop. A
  camera that stops publishing never stalls the others: a group goes out when every camera has
  reported or when it has waited ``timeout`` seconds (of the caller's clock), whichever comes first.
* :func:`sanitize_observations` — drops what must never reach the estimators (NaN corners,
  degenerate quads, duplicate ids in one image, ignored ids) and says why. The pipelines
  (:mod:`pipeline`) call it once, where detections enter; the estimators rely on it.

These types are shared by the simulator, the detector, the mapper and the localizer.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Collection, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from .camera import CameraModel
from .markers import finite_quad_ok, quads_ok

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


def simultaneous_parts(frame: RingFrame, spread: float) -> List[RingFrame]:
    """``frame`` split into ring frames of the cameras exposed together: sorted by stamp, a part
    holds the cameras within ``spread`` (s) of its earliest one (free-running cameras: one part per
    phase; synchronized ones: ``frame`` itself). ``missing`` stays with the first part."""
    order = sorted(frame.cameras.values(), key=lambda cf: (cf.stamp, cf.camera))
    parts: List[RingFrame] = []
    for cf in order:
        if not parts or cf.stamp - parts[-1].stamp > spread:
            parts.append(RingFrame(stamp=cf.stamp, missing=[] if parts else list(frame.missing)))
        parts[-1].cameras[cf.camera] = cf
    return parts


_NEVER = -math.inf  # a camera's last_seen before its first frame
_FLOAT64 = np.dtype(np.float64)  # native float64 (another byte order is another dtype object)

#: ``slop`` value that derives the ring frame's window from the cameras' stamps (the default).
AUTO_SLOP = "auto"


def parse_slop(value: Union[float, str], key: str = "slop") -> Optional[float]:
    """``input/slop`` as the assembler takes it: None for ``auto``, else a number of seconds >= 0.

    Raises ValueError naming ``key`` on anything else (a negative or non-finite number, another word).
    """
    if isinstance(value, str):
        text = value.strip().lower()
        if text == AUTO_SLOP:
            return None
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{key}: expected 'auto' or a number of seconds >= 0, got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{key}: expected 'auto' or a number of seconds >= 0, got {value!r}")
    return float(value)


@dataclass
class _Group:
    """A ring frame being assembled, with what the assembler needs to know about it."""

    frame: RingFrame
    arrived: float        # caller's clock at its first member
    deadline: float       # caller's clock when it goes out incomplete
    lo: float             # stamps in [lo, hi) belong to it (auto), or lo..hi is its members' extent
    hi: float

    def accepts(self, camera: str, stamp: float, slop: Optional[float]) -> bool:
        if camera in self.frame.cameras:
            return False
        if slop is None:
            return self.lo <= stamp < self.hi
        return max(self.hi, stamp) - min(self.lo, stamp) <= slop


def _group_stamp(group: _Group) -> float:
    return group.frame.stamp


class RingFrameAssembler:
    """Group per-camera frames into ring frames by stamp.

    A ring frame holds each camera at most once. Two ways of grouping (``slop``):

    * ``"auto"`` (the default): for synchronized and free-running cameras alike, without tuning.
      The cameras' frame period ``P`` is measured from their stamps (per camera the median of
      its last 3 stamp differences, then the median over the cameras: a camera that drops frames
      or a dead one does not move it; a rate change is followed within about 3 frames). The
      cameras' phases (their latest stamps modulo ``P``) leave gaps on the circle of one period;
      the ring frames' boundary is put in the middle of the largest gap (kept while its gap stays
      at least 3/4 of the largest: no flapping between two similar gaps), and a ring frame is the
      stamps in one period ``[b + kP, b + (k+1)P)``. So synchronized cameras get a window centred
      on their common stamp, half a period of margin each side, and free-running cameras with
      any phases get one frame each, with half the largest phase gap of margin for their
      jitter. Until a period has been measured (each camera's first frame) the window is
      ``AUTO_START_SLOP``. The timeout of a frame counts from its first member's arrival plus
      the time the cameras' phases still spread after that member (free-running cameras report
      over up to a period; synchronized ones at once: their timeout is unchanged).
    * a number ``s`` (seconds): a ring frame holds frames whose stamps differ by at most ``s``
      (its members' extent, max - min, is <= ``s``). For synchronized cameras, or a known spread.

    In both, a frame that belongs to a ring frame that already went out (its camera is missing
    there and its stamp is within that frame's window), or stamped before the last ring frame, is
    late and dropped (``dropped_late``); a camera's *next* frame is never late: it opens a new ring
    frame.

    Args:
        cameras: the names of the cameras expected in each frame.
        slop: ``"auto"``, or the largest stamp difference (s) within one ring frame.
        timeout: a group that is still incomplete this long (s, caller's clock) after its first
            member arrived goes out without the missing cameras (auto: plus the phase spread still
            to come, see above).
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

    #: auto: the window (s) before the cameras' period is known (their first frames).
    AUTO_START_SLOP = 0.03
    #: auto: stamp differences longer than this (s) are gaps (a pause, a jump), not a period.
    AUTO_MAX_PERIOD = 2.0
    #: auto: the stamps per camera that measure its period and phase.
    HISTORY = 5

    def __init__(self, cameras: Sequence[str], slop: Union[float, str] = AUTO_SLOP, timeout: float = 0.25,
                 max_pending: Optional[int] = None, silence: Optional[float] = 1.0, late_by_clock: bool = False):
        if not cameras:
            raise ValueError("RingFrameAssembler needs at least one camera name")
        fixed = parse_slop(slop)
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0, got {timeout!r}")
        self.cameras = list(cameras)
        #: the fixed slop (s), or None for auto.
        self.slop: Optional[float] = fixed
        self.timeout = float(timeout)
        self.max_pending = max(8, int(np.ceil(50.0 * self.timeout))) if max_pending is None else int(max_pending)
        self.silence = silence
        self.late_by_clock = bool(late_by_clock)
        self._first_seen: Optional[float] = None
        self._pending: List[_Group] = []  # stamp order
        self._last: Optional[_Group] = None  # the newest ring frame that went out
        self._last_emitted = -np.inf
        self._stamps: Dict[str, List[float]] = {}    # camera -> its last HISTORY stamps, oldest first
        self._diffs: Dict[str, List[float]] = {}     # camera -> its last HISTORY stamp differences
        self._boundary: Optional[float] = None       # auto: a stamp on a ring frame boundary
        self.last_seen: Dict[str, float] = {}   # camera -> caller's clock at its last frame
        self.dropped_late = 0
        #: frames with a NaN or infinite stamp (dropped).
        self.dropped_bad_stamp = 0
        self.time_jumps = 0
        #: Ring frames that went out without every camera, by reason: ``timeout`` (waited
        #: ``timeout`` s), ``silent`` (the missing cameras were silent for ``silence`` s),
        #: ``overtaken`` (a newer frame completed before it, or more than ``max_pending`` waited).
        self.incomplete: Dict[str, int] = {"timeout": 0, "silent": 0, "overtaken": 0}

    def reset(self) -> None:
        """Forget the pending groups and the stamp history (a time jump)."""
        self._pending.clear()
        self._last = None
        self._last_emitted = -np.inf
        self._stamps.clear()
        self._diffs.clear()
        self._boundary = None

    # --- the cameras' timing (auto) ---------------------------------------------------------

    def _record_stamp(self, camera: str, stamp: float) -> None:
        stamps = self._stamps.setdefault(camera, [])
        if stamps and stamp <= stamps[-1]:
            return  # a repeated or older stamp says nothing about the period
        if stamps and stamp - stamps[-1] <= self.AUTO_MAX_PERIOD:
            diffs = self._diffs.setdefault(camera, [])
            diffs.append(stamp - stamps[-1])
            del diffs[:-self.HISTORY]
        elif stamps:
            stamps.clear()  # a gap: the older stamps say nothing about the phase
        stamps.append(stamp)
        del stamps[:-self.HISTORY]

    def timing(self) -> Optional[Tuple[float, float]]:
        """The cameras' frame period and stamp jitter (s, 1 sigma) measured from their stamps (auto), or
        None before a period is known: the median of every camera's last stamp differences, and
        their spread (1.4826 MAD / sqrt 2)."""
        pooled: List[float] = []
        for d in self._diffs.values():
            pooled += d   # (lists joined and sorted in place: a generator per number cost more)
        if not pooled:
            return None
        pooled.sort()
        n = len(pooled)
        period = 0.5 * (pooled[(n - 1) // 2] + pooled[n // 2])
        dev = sorted([abs(x - period) for x in pooled])
        return period, 1.4826 * 0.5 * (dev[(n - 1) // 2] + dev[n // 2]) / math.sqrt(2.0)

    def _phases(self, stamp: float, period: float) -> List[float]:
        """The cameras' phases in [0, period) relative to ``stamp``, sorted.

        A camera's phase is the circular mean of its last stamps' (one stamp's jitter would move
        the gaps frame by frame); a camera whose newest stamp is more than 2 periods from
        ``stamp`` (dead, lagging) has none.
        """
        phases = []
        # (the loop's constants and functions bound once: it runs over every stamp of every camera,
        # once per ring frame; the same expressions, the same numbers)
        two_pi, span, cos, sin = 2.0 * math.pi, (self.HISTORY + 0.5) * period, math.cos, math.sin
        for stamps in self._stamps.values():
            newest = stamps[-1]
            if abs(newest - stamp) > 2.0 * period:
                continue
            c = sn = 0.0
            for t in stamps:
                if newest - t <= span:
                    angle = two_pi * (t - stamp) / period
                    c += cos(angle)
                    sn += sin(angle)
            phases.append((math.atan2(sn, c) / two_pi * period) % period)
        return sorted(phases) or [0.0]

    def _window(self, stamp: float, period: float, jitter: float) -> Tuple[float, float, float]:
        """The auto window ``[lo, hi)`` of one period that holds ``stamp``, and the cameras' phase spread (s).

        The boundary between ring frames goes in the middle of the largest gap between the
        cameras' phases. Once placed it stays in its gap (following the gap's middle) while that
        gap is at least 0.8 of the largest, or at least half of it with a margin of 2 jitters each
        side: two similar gaps do not take turns, and each change of gap costs a split frame.
        """
        phases = self._phases(stamp, period)
        n = len(phases)
        gaps = [(phases[(i + 1) % n] - p) % period for i, p in enumerate(phases)] if n > 1 else [period]
        best = max(range(n), key=gaps.__getitem__)
        boundary = stamp + phases[best] + 0.5 * gaps[best]
        spread = period - gaps[best]
        if self._boundary is not None:
            held = (self._boundary - stamp) % period
            for i, p in enumerate(phases):
                if (held - p) % period < gaps[i]:  # the held boundary lies in gap i
                    if gaps[i] >= 0.8 * gaps[best] or (gaps[i] >= 0.5 * gaps[best] and gaps[i] >= 4.0 * jitter):
                        # Keep it, moved half the way to the gap's middle (the phases move a
                        # little with the jitter; a slow drift of the cameras' rates is followed).
                        middle = p + 0.5 * gaps[i]
                        boundary = stamp + held + 0.5 * ((middle - held + 0.5 * period) % period - 0.5 * period)
                        spread = period - gaps[i]
                    break
        self._boundary = boundary
        lo = boundary + math.floor((stamp - boundary) / period) * period
        return lo, lo + period, spread

    # --- assembly ---------------------------------------------------------------------------

    def add(self, frame: CameraFrame, now: float) -> List[RingFrame]:
        """Take one camera's frame (``now`` is the caller's clock, s); return finished ring frames."""
        if frame.camera not in self.cameras:
            logger.debug("ignoring frame from unknown camera %s", frame.camera)
            return []
        if not math.isfinite(frame.stamp):
            self.dropped_bad_stamp += 1
            return self.poll(now)
        if self.silence is not None and (not self.last_seen or max(self.last_seen.values()) < now - self.silence):
            # Start-up, or every camera was silent: wait for all of them again while they come back.
            self._first_seen = now
        self.last_seen[frame.camera] = now
        stamp = frame.stamp
        if stamp < self._last_emitted - 1.0 and not (self.late_by_clock and now - stamp > 1.0):
            # Time went backwards by more than a second (a bag loop, a clock reset): start over.
            # With late_by_clock, a stamp that is old by the caller's clock too is a late message,
            # not a jump (dropped below): one lagging camera must not reset everybody's frames.
            self.time_jumps += 1
            logger.warning("time jumped back from %.3f to %.3f s; resetting frame assembly",
                           self._last_emitted, stamp)
            self.reset()
        if self._is_late(frame.camera, stamp):
            self.dropped_late += 1
            return self.poll(now)
        self._record_stamp(frame.camera, stamp)
        group = next((g for g in self._pending if g.accepts(frame.camera, stamp, self.slop)), None)
        if group is None:
            group = self._open(frame.camera, stamp, now)
            if group is None:
                self.dropped_late += 1
                return self.poll(now)
        group.frame.cameras[frame.camera] = frame
        group.frame.stamp = min(group.frame.stamp, stamp)
        if self.slop is not None:
            group.lo, group.hi = min(group.lo, stamp), max(group.hi, stamp)
        if len(self._pending) > 1:
            self._pending.sort(key=_group_stamp)
        return self.poll(now)

    def _is_late(self, camera: str, stamp: float) -> bool:
        """Stamped at or before the newest ring frame that went out (it would come out of order)."""
        return self._last is not None and stamp <= self._last.frame.stamp

    def _open(self, camera: str, stamp: float, now: float) -> Optional[_Group]:
        """A new group for this frame, or None when it belongs to the ring frame that already went out."""
        last = self._last
        if last is not None and last.accepts(camera, stamp, self.slop):
            # Its camera is missing from that frame and its stamp is in that frame's window: a
            # frame of its own would repeat that frame with one camera. (A camera's next frame is
            # not accepted there: its camera is in it.)
            return None
        timing = self.timing() if self.slop is None else None
        if timing is None:
            width = self.slop if self.slop is not None else self.AUTO_START_SLOP
            lo, hi, spread = stamp, stamp, 0.0
            if self.slop is None:  # auto, before the period is known: a window ahead of the frame
                lo, hi = stamp - 0.5 * width, stamp + 0.5 * width
        else:
            lo, hi, spread = self._window(stamp, *timing)
        # Free-running cameras report over their phase spread: the timeout starts after it.
        extra = max(0.0, min(spread, hi - stamp)) if self.slop is None else 0.0
        group = _Group(RingFrame(stamp=stamp), arrived=now, deadline=now + self.timeout + extra, lo=lo, hi=hi)
        self._pending.append(group)
        return group

    def poll(self, now: float) -> List[RingFrame]:
        """Return the groups that are complete or timed out, and every older group before them."""
        if not self._pending:
            return []  # (the poll timer's usual case: nothing waits)
        ready_upto = -1
        awaited = self._awaited(now)
        for i, g in enumerate(self._pending):
            if awaited.issubset(g.frame.cameras) or now >= g.deadline:
                ready_upto = i
        overflow = len(self._pending) - self.max_pending
        ready_upto = max(ready_upto, overflow - 1)
        out = []
        for g in self._pending[: ready_upto + 1]:
            rf = g.frame
            rf.missing = [c for c in self.cameras if c not in rf.cameras]
            if rf.missing:
                # Why it went out incomplete (counted for the nodes' summaries and diagnostics).
                if now >= g.deadline:
                    self.incomplete["timeout"] += 1
                elif awaited.issubset(rf.cameras):
                    self.incomplete["silent"] += 1
                else:
                    self.incomplete["overtaken"] += 1
            out.append(rf)
            if rf.stamp >= self._last_emitted:
                self._last_emitted = rf.stamp
                self._last = g
        del self._pending[: ready_upto + 1]
        return out

    def _awaited(self, now: float) -> set:
        """The cameras a group waits for: all, less those silent for ``silence`` seconds.

        For ``silence`` seconds after start-up, or after every camera was silent, all cameras are
        awaited: they come up one by one, and the first frame must not go out with one camera.
        """
        silence = self.silence
        if silence is None or (self._first_seen is not None and now - self._first_seen < silence):
            return set(self.cameras)
        seen = self.last_seen.get
        return {c for c in self.cameras if now - seen(c, _NEVER) <= silence}

    def silent_cameras(self, now: float, silence: float) -> List[str]:
        """Cameras that have sent nothing for ``silence`` seconds (or never)."""
        return [c for c in self.cameras if now - self.last_seen.get(c, -np.inf) > silence]


#: Up to this many detections in one image :func:`sanitize_observations` checks them on Python
#: floats (one pass per detection, as :func:`markers.quad_ok_scalar` does, finiteness tested once),
#: more with numpy: the same decisions, without the fixed cost of about twenty small numpy calls
#: per message (the localizer sanitizes each camera's two or three detections on every message:
#: 46 us per message with numpy, 8 us so).
SCALAR_SANITIZE = 16


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
    for obs in observations:
        if obs.marker_id in ignore:
            drop("ignored")
            continue
        if obs.marker_id < 0:
            drop("negative id")   # no dictionary has one: a corrupt message
            continue
        candidates.append(obs)
    if not candidates:
        return [], reasons
    if len(candidates) <= SCALAR_SANITIZE and all([_is_float_quad(o.corners) for o in candidates]):
        # What the nodes' conversion gives: each quad's Python floats straight from its array.
        kept = _sanitize_scalar(candidates, [o.corners.tolist() for o in candidates], None, width, height,
                                min_area_px, drop)
    else:
        # One array for the whole image (a few numpy calls per image, not per marker: this runs
        # for every camera message); the marker-by-marker check only when some corners are not (4, 2).
        try:
            q = np.array([o.corners for o in candidates], dtype=np.float64)
        except (ValueError, TypeError):
            q = None
        if q is not None and q.shape == (len(candidates), 4, 2) and len(candidates) <= SCALAR_SANITIZE:
            kept = _sanitize_scalar(candidates, q.tolist(), q, width, height, min_area_px, drop)
        else:
            kept = _sanitize_array(candidates, q, width, height, min_area_px, drop)
    ids = [o.marker_id for o in kept]
    if len(set(ids)) < len(ids):
        counts = Counter(ids)
        dups = {i for i, n in counts.items() if n > 1}
        reasons["duplicate id"] = sum(counts[i] for i in dups)
        kept = [o for o in kept if o.marker_id not in dups]
    return kept, reasons


def _as_float_observation(obs: MarkerObservation, corners: np.ndarray) -> MarkerObservation:
    """``obs`` itself when its corners are a float64 array, else a copy with ``corners`` (float64)."""
    if isinstance(obs.corners, np.ndarray) and obs.corners.dtype == np.float64:
        return obs
    return MarkerObservation(int(obs.marker_id), corners)


def _is_float_quad(corners) -> bool:
    """Whether ``corners`` is a plain float64 numpy array of shape (4, 2) (kept as it is)."""
    return type(corners) is np.ndarray and corners.dtype is _FLOAT64 and corners.shape == (4, 2)


def _sanitize_scalar(candidates: List[MarkerObservation], quads: List[list], q: Optional[np.ndarray],
                     width: Optional[int], height: Optional[int], min_area_px: float,
                     drop) -> List[MarkerObservation]:
    """:func:`sanitize_observations`' checks for a few detections with corners ``quads`` (k lists
    of 4 [x, y]), on Python floats (the same IEEE arithmetic as :func:`_sanitize_array`'s, in the
    same order: non-finite, then outside the image, then degenerate). ``q``: the same as a (k, 4, 2)
    float64 array, for the observations whose corners are not one already; None when all are."""
    inside = None
    if width and height:
        size_x, size_y = float(width), float(height)
        inside = (0.5 * size_x, 0.5 * size_y, 1.5 * size_x, 1.5 * size_y)
    kept = []
    isfinite = math.isfinite
    for k, quad in enumerate(quads):
        (x0, y0), (x1, y1), (x2, y2), (x3, y3) = quad
        if not (isfinite(x0) and isfinite(y0) and isfinite(x1) and isfinite(y1) and isfinite(x2)
                and isfinite(y2) and isfinite(x3) and isfinite(y3)):
            drop("non-finite")
            continue
        if inside is not None:
            cx, cy, ex, ey = inside
            if not (abs(x0 - cx) <= ex and abs(x1 - cx) <= ex and abs(x2 - cx) <= ex and abs(x3 - cx) <= ex
                    and abs(y0 - cy) <= ey and abs(y1 - cy) <= ey and abs(y2 - cy) <= ey and abs(y3 - cy) <= ey):
                drop("outside image")
                continue
        if not finite_quad_ok(x0, y0, x1, y1, x2, y2, x3, y3, min_area_px):
            drop("degenerate")
            continue
        kept.append(candidates[k] if q is None else _as_float_observation(candidates[k], q[k]))
    return kept


def _sanitize_array(candidates: List[MarkerObservation], q: Optional[np.ndarray], width: Optional[int],
                    height: Optional[int], min_area_px: float, drop) -> List[MarkerObservation]:
    """:func:`sanitize_observations`' checks with numpy (many detections, or corners of odd shapes)."""
    if q is not None and q.shape == (len(candidates), 4, 2):
        finite = np.isfinite(q).all(axis=(1, 2))
        drop("non-finite", int(np.count_nonzero(~finite)))
        candidates = [_as_float_observation(o, q[k]) for k, o in enumerate(candidates) if finite[k]]
        q = q[finite]
    else:
        checked = []
        arrays: List[np.ndarray] = []
        for obs in candidates:
            c = np.asarray(obs.corners, dtype=np.float64)
            if c.shape != (4, 2) or not np.all(np.isfinite(c)):
                drop("non-finite")
                continue
            checked.append(obs if c is obs.corners else MarkerObservation(int(obs.marker_id), c))
            arrays.append(c)
        candidates = checked
        q = np.stack(arrays) if arrays else None
    if not candidates:
        return []
    ok = np.ones(len(candidates), dtype=bool)
    if width and height:
        size = np.array([width, height], dtype=np.float64)
        ok = (np.abs(q - 0.5 * size) <= 1.5 * size).all(axis=(1, 2))
        drop("outside image", int(np.count_nonzero(~ok)))
    good = quads_ok(q, min_area_px)
    drop("degenerate", int(np.count_nonzero(ok & ~good)))
    return [o for o, k in zip(candidates, ok & good) if k]
