"""The core's ``logging`` records to rosout: a node calls :func:`install` once after ``init_node``.

The core logs through ``logging.getLogger(__name__)`` and throttles per-message problems itself
(:class:`aruco_ring_localization.throttle.ThrottledWarnings`), so this handler forwards every
record as it is: DEBUG -> ``rospy.logdebug``, INFO -> ``loginfo``, WARNING -> ``logwarn``,
ERROR and above -> ``logerr``. The package logger stops propagating to the root logger (rospy
writes rosout's records to the node's log file already: no line twice).
"""
from __future__ import annotations

import logging

PACKAGE_LOGGER = "aruco_ring_localization"


class RospyHandler(logging.Handler):
    """A logging handler that hands each record to rospy's logger of the same level."""

    def emit(self, record: logging.LogRecord) -> None:
        import rospy

        try:
            text = self.format(record)
        except Exception:  # noqa: BLE001 - logging's contract: a bad record never raises
            self.handleError(record)
            return
        if record.levelno >= logging.ERROR:
            rospy.logerr(text)
        elif record.levelno >= logging.WARNING:
            rospy.logwarn(text)
        elif record.levelno >= logging.INFO:
            rospy.loginfo(text)
        else:
            rospy.logdebug(text)


def install(level: int = logging.INFO) -> logging.Handler:
    """Route the package's log records (``aruco_ring_localization.*``) to rosout; idempotent."""
    log = logging.getLogger(PACKAGE_LOGGER)
    for h in log.handlers:
        if isinstance(h, RospyHandler):
            return h
    handler = RospyHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False
    return handler
