"""Lockstep between the simulator's clock and its consumers (:class:`FrameGate`).

In image mode the detectors may take longer per frame than the simulator. With a simulated
clock nothing forces the simulator to go faster than its consumers: before it advances the
clock to the next frame it can wait until every camera's detector has answered the current one
(its ``fiducial_vertices`` carry the frame's stamp). Then no frame is ever dropped, whatever the
CPU; the simulated clock just runs slower than the wall clock. A timeout keeps a dead detector
from stopping the simulation.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Dict, Iterable, List

logger = logging.getLogger(__name__)


class FrameGate:
    """Waits until every expected source has reported a stamp at least as new as a frame's.

    Args:
        sources: names of the sources (cameras) to wait for.
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

    def missing(self, stamp: float) -> List[str]:
        """Sources that have not yet reported ``stamp`` (or a newer one)."""
        with self._cond:
            return self._missing(stamp)

    def _missing(self, stamp: float) -> List[str]:
        return [s for s in self.sources if self._latest.get(s, float("-inf")) < stamp - self.tolerance]

    def wait(self, stamp: float, timeout: float) -> List[str]:
        """Block until every source has reported ``stamp``, at most ``timeout`` wall seconds.

        Returns the sources still missing (empty when all answered in time).
        """
        deadline = time.monotonic() + max(0.0, float(timeout))
        with self._cond:
            while True:
                missing = self._missing(stamp)
                remaining = deadline - time.monotonic()
                if not missing or remaining <= 0:
                    return missing
                self._cond.wait(remaining)
