"""The simulator's own clock (:class:`SimClock`) and its lockstep with the consumers (:class:`FrameGate`).

With a simulated clock nothing forces the simulator to go faster than its consumers (the
detectors in image mode, the localizer, ...): before it advances the clock to the next frame it
can wait until every consumer has answered the current one (a message carrying the frame's
stamp). Then no frame is ever dropped, whatever the CPU; the simulated clock just runs slower
than the wall clock. A timeout keeps a dead consumer from stopping the simulation.

While it waits, the clock is not frozen: it creeps forward by a fraction of a frame period
(never reaching the next frame's stamp), because the nodes' ROS-time timers (an assembler's
flush of incomplete frames, a diagnostics period) only fire while the clock moves, as they would
on a robot.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Dict, Iterable, List, Optional

logger = logging.getLogger(__name__)


class FrameGate:
    """Waits until every expected source has reported a stamp at least as new as a frame's.

    Args:
        sources: names of the sources (cameras, topics) to wait for.
        tolerance: stamps within this many seconds of the frame's count as the frame's, s.

    Thread-safe: :meth:`report` is called from subscriber threads, :meth:`wait` from the loop.
    """

    def __init__(self, sources: Iterable[str], tolerance: float = 1e-6):
        self.sources = list(sources)
        self.tolerance = float(tolerance)
        self._latest: Dict[str, float] = {}
        self._cond = threading.Condition()

    def report(self, source: str, stamp: float) -> None:
        """A source answered the frame stamped ``stamp`` (s); unknown sources are ignored."""
        if source not in self.sources:
            return
        with self._cond:
            if stamp > self._latest.get(source, float("-inf")):
                self._latest[source] = float(stamp)
            self._cond.notify_all()

    def reset(self) -> None:
        """Forget every report (the clock jumped back: old stamps would hide the new frames')."""
        with self._cond:
            self._latest.clear()

    def missing(self, stamp: float, sources: Optional[Iterable[str]] = None) -> List[str]:
        """Sources (of ``sources``, default all) that have not yet reported ``stamp`` or a newer one."""
        with self._cond:
            return self._missing(stamp, self.sources if sources is None else list(sources))

    def _missing(self, stamp: float, sources: List[str]) -> List[str]:
        return [s for s in sources if self._latest.get(s, float("-inf")) < stamp - self.tolerance]

    def wait(self, stamp: float, timeout: float, active: Optional[Callable[[], Iterable[str]]] = None,
             idle: Optional[Callable[[float], None]] = None, idle_period: float = 0.05) -> List[str]:
        """Block until every source has reported ``stamp``, at most ``timeout`` wall seconds.

        Args:
            active: returns the sources to wait for now (e.g. the connected ones); called again
                on every wake-up, so a source that disconnects stops being waited for. Default:
                all of them.
            idle: called with the wall seconds waited so far every ``idle_period`` s while waiting
                (the simulator creeps its clock there).

        Returns the sources still missing (empty when all answered in time).
        """
        t0 = time.monotonic()
        deadline = t0 + max(0.0, float(timeout))
        while True:
            names = self.sources if active is None else [s for s in active() if s in self.sources]
            with self._cond:
                missing = self._missing(stamp, names)
                remaining = deadline - time.monotonic()
                if not missing or remaining <= 0:
                    return missing
                self._cond.wait(min(remaining, idle_period))
            if idle is not None:
                idle(time.monotonic() - t0)


class SimClock:
    """The simulated time of a simulator that publishes ``/clock``.

    Frames are exactly ``dt`` apart (``start + k dt``, plus any jump); :meth:`jump` moves the
    clock before the next frame (a negative jump is a bag loop, for fault tests); :meth:`creep`
    is the time to publish while waiting for the consumers of the current frame.

    Args:
        start: the first frame's time, s (> 0: rospy treats 0 as "not set").
        dt: frame period, s.
        creep_rate: simulated seconds per wall second while waiting.
        creep_limit: fraction of ``dt`` the clock may creep past the current frame.
    """

    def __init__(self, start: float, dt: float, creep_rate: float = 0.2, creep_limit: float = 0.4):
        self.start = float(start)
        self.dt = float(dt)
        self.creep_rate = float(creep_rate)
        self.creep_limit = float(creep_limit)
        self.now: Optional[float] = None      # the current frame's time (None before the first)
        self._base = self.start               # time of frame 0, jumps included
        self._frames = 0
        self._jump = 0.0
        self._lock = threading.Lock()

    def request_jump(self, seconds: float) -> None:
        """Add ``seconds`` to the clock at the next frame (thread-safe; repeated requests add up)."""
        with self._lock:
            self._jump += float(seconds)

    def advance(self) -> float:
        """The next frame's time (the first call gives ``start``), to the nanosecond.

        Frame times are computed from the frame count (no accumulated rounding). A pending jump
        that would bring the time to zero or below is refused (logged): rospy cannot represent it.
        """
        with self._lock:
            jump, self._jump = self._jump, 0.0
        self._frames += 1
        t = self._base + jump + (self._frames - 1) * self.dt
        if jump and t <= 0:
            logger.warning("simulated clock: a jump of %.3f s would bring it to %.3f s; ignored", jump, t)
            jump = 0.0
        self._base += jump
        self.now = round(self._base + (self._frames - 1) * self.dt, 9)
        return self.now

    def creep(self, waited: float) -> float:
        """The time to publish after waiting ``waited`` wall seconds for the current frame's consumers."""
        if self.now is None:
            return self.start
        return self.now + min(self.creep_rate * max(0.0, waited), self.creep_limit * self.dt)
