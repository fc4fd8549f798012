"""Stops: where the reference stood still, and the errors at each stop (the rows of Tables I, II).

The paper measures the robot at rest at marked positions and orientations (§III-B). From a
trajectory: :func:`detect_stops` finds the intervals in which the reference stayed within a
tolerance; :func:`stop_errors` gives one :class:`StopError` per stop (median of the matched poses
inside it, yaw by circular mean). Planar poses (x, y, yaw) in m and rad; errors estimate minus
reference (:func:`trajectories.pose_errors`). evo has no notion of stops.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

from .. import geometry as geo
from .trajectories import MatchedPairs, error_statistics, pose_errors

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Stop:
    """An interval [start, end] (s) during which the reference stood still."""

    start: float
    end: float

    @property
    def duration(self) -> float:
        return self.end - self.start


def detect_stops(stamps: np.ndarray, ref: np.ndarray, min_duration: float = 2.0, pos_tol: float = 0.01,
                 yaw_tol: float = np.radians(0.5), settle: float = 0.0) -> List[Stop]:
    """Intervals where the reference pose stays within a tolerance for at least ``min_duration``.

    A stop grows while every pose stays within ``pos_tol`` m and ``yaw_tol`` rad of the pose that
    opened it. ``settle`` s are cut from the start of each stop (a filter catching up after the
    motion) and the stop is kept only if ``min_duration`` remains.

    Args:
        stamps: (N,) increasing seconds.
        ref: (N, 3) reference poses.
    """
    s = np.asarray(stamps, dtype=np.float64).reshape(-1)
    r = np.asarray(ref, dtype=np.float64).reshape(-1, 3)
    stops: List[Stop] = []
    i, n = 0, len(s)
    while i < n:
        j = i + 1
        while j < n and np.hypot(*(r[j, :2] - r[i, :2])) <= pos_tol and abs(geo.angle_diff(r[j, 2], r[i, 2])) <= yaw_tol:
            j += 1
        start, end = s[i] + settle, s[j - 1]
        if end - start >= min_duration:
            stops.append(Stop(float(start), float(end)))
        i = j
    return stops


@dataclass(frozen=True)
class StopError:
    """The errors at one stop (a row of Table I or II).

    Attributes:
        label: row name ("1", "P3", ...).
        ref: (3,) reference pose (x m, y m, yaw rad): the median over the stop.
        est: (3,) estimated pose over the stop (median, yaw by circular mean).
        n: matched poses averaged.
        start, end: s.
    """

    label: str
    ref: np.ndarray
    est: np.ndarray
    n: int = 1
    start: float = float("nan")
    end: float = float("nan")
    extra: Dict[str, float] = field(default_factory=dict)

    @property
    def errors(self) -> np.ndarray:
        """(4,) dx m, dy m, Euclidean m, dyaw rad."""
        return pose_errors(self.ref, self.est)[0]

    @property
    def ok(self) -> bool:
        """False for a stop without an estimate (``est`` is NaN)."""
        return bool(np.all(np.isfinite(self.est)))


def robust_pose(poses: np.ndarray) -> np.ndarray:
    """(3,) median x, y and circular-mean yaw of (N, 3) planar poses."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    return np.array([float(np.median(p[:, 0])), float(np.median(p[:, 1])), geo.circular_mean(p[:, 2])])


def stop_errors(pairs: MatchedPairs, stops: Iterable[Stop], labels: Optional[Sequence[str]] = None) -> List[StopError]:
    """One :class:`StopError` per stop that has matched poses (median of the poses inside it)."""
    rows: List[StopError] = []
    for k, stop in enumerate(stops):
        inside = (pairs.stamps >= stop.start) & (pairs.stamps <= stop.end)
        if not np.any(inside):
            logger.warning("stop %d [%.2f, %.2f] s has no matched estimate; skipped", k + 1, stop.start, stop.end)
            continue
        label = labels[k] if labels is not None and k < len(labels) else str(k + 1)
        rows.append(StopError(label, robust_pose(pairs.ref[inside]), robust_pose(pairs.est[inside]),
                              int(inside.sum()), stop.start, stop.end))
    return rows


def summarize(rows: Sequence[StopError]) -> Dict[str, float]:
    """Statistics over stops: position error (cm) median/mean/max, |yaw| error (deg) mean/max."""
    rows = [r for r in rows if r.ok]
    if not rows:
        return {"n": 0}
    return error_statistics(np.stack([r.errors for r in rows]))
