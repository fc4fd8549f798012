"""The simulator's route as a rostest sees it: the waypoints it has held (``sim/at_waypoint``).

Shared by the rostests that let the simulator drive its whole route and then ask a node for its
result (the mapper's ``~save_map``, a recorded bag for ``calibrate-ring``).
"""
from __future__ import annotations

import threading
import time
from typing import Callable, List

import rospy
from std_msgs.msg import Int32


class HeldWaypoints:
    """The distinct waypoint indices the simulator held, in order (-1: the route finished)."""

    def __init__(self, topic: str = "/sim/at_waypoint") -> None:
        self._lock = threading.Lock()
        self._held: List[int] = []
        self._sub = rospy.Subscriber(topic, Int32, self._on_waypoint, queue_size=100)

    def _on_waypoint(self, msg: Int32) -> None:
        with self._lock:
            if not self._held or self._held[-1] != msg.data:
                self._held.append(int(msg.data))

    @property
    def held(self) -> List[int]:
        with self._lock:
            return list(self._held)

    def wait_until(self, done: Callable[[List[int]], bool], timeout: float, what: str) -> List[int]:
        """Wait (wall time: simulated time may run at any speed) until ``done(held)``.

        Raises:
            AssertionError: not done within ``timeout`` s, naming ``what`` and the waypoints held.
        """
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not rospy.is_shutdown():
            held = self.held
            if done(held):
                return held
            rospy.rostime.wallsleep(0.05)
        raise AssertionError(f"the simulator did not {what} within {timeout:.0f} s: held {self.held}")

    def wait_for_route_end(self, last: int, timeout: float) -> List[int]:
        """Held the last station, then finished (the mapping route)."""
        return self.wait_until(lambda h: h[-2:] == [last, -1], timeout, f"go through the {last + 1} stations")

    def wait_for_waypoint(self, index: int, timeout: float) -> List[int]:
        """Held waypoint ``index`` (routes that end there)."""
        return self.wait_until(lambda h: index in h, timeout, f"reach waypoint {index}")
