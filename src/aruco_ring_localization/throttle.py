"""Throttled warnings: one line per problem per period, however many messages repeat it.

Per-message problems (a camera without camera_info, malformed detections, a rejected measurement)
arrive at the camera rate; a log line each would bury everything else. :class:`ThrottledWarnings`
lets one line per *problem key* through per ``period`` seconds and counts the rest, so one bad
field never hides another and a test can count what was said. The nodes send the core's
``logging`` records to rosout (``ros/log_bridge.py``); the throttling happens here, in the core.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional

#: Seconds between two lines about the same problem.
WARN_PERIOD = 5.0


class ThrottledWarnings:
    """One warning per problem key per ``period`` seconds, through ``sink`` (e.g. ``logger.warning``).

    Args:
        sink: called with the message text.
        period: seconds between two lines with the same key.
        clock: seconds, used when a call gives no ``now`` (monotonic by default).

    Attributes:
        counts: key -> how many times the problem happened (said or not).
        said: key -> how many lines went out.
    """

    def __init__(self, sink: Callable[[str], None], period: float = WARN_PERIOD,
                 clock: Callable[[], float] = time.monotonic):
        self.sink = sink
        self.period = float(period)
        self.clock = clock
        self._last: Dict[str, float] = {}
        self.counts: Dict[str, int] = {}
        self.said: Dict[str, int] = {}

    def __call__(self, key: str, message: str, now: Optional[float] = None) -> bool:
        """Count problem ``key``; say ``message`` unless it was said less than ``period`` ago.

        ``now`` is the caller's clock (s; a bag's time offline). A clock that went backwards
        (a bag loop) lets the line through. Returns True when the line went out.
        """
        self.counts[key] = self.counts.get(key, 0) + 1
        t = self.clock() if now is None else float(now)
        last = self._last.get(key)
        if last is not None and 0.0 <= t - last < self.period:
            return False
        self._last[key] = t
        self.said[key] = self.said.get(key, 0) + 1
        n = self.counts[key]
        self.sink(message if n == 1 else f"{message} ({n} times so far)")
        return True
