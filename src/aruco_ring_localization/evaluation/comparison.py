"""Live comparison of our pose with a reference (gmapping, ground truth): the comparison node's core.

The comparison node (:mod:`aruco_ring_localization.ros.comparison`) feeds this class time-matched planar pose pairs:
the reference robot pose in the reference map frame (gmapping's ``map -> base_link``) and ours
in our marker map frame (``aruco_map -> aruco_base_link``). The two map frames differ by a fixed
unknown SE(2) transform ``T_ref_est`` (where gmapping started vs where our reference marker is):

- it is estimated by least squares over the pairs (:func:`trajectories.align_se2`, evo's Umeyama in 2D;
  re-estimated as pairs arrive, from at most ``max_pairs`` pairs thinned evenly over time), or
  given by the user (``alignment`` = (x, y, yaw));
- the live errors are ``T_ref_est * est - ref``: x, y, Euclidean (m), yaw (rad);
- a *stop* is recorded when the reference stood still for ``still_time`` s (once per still
  period, with the poses of that period) or on request (:meth:`record_stop`, the poses of the
  last ``record_window`` s);
- :meth:`tables` gives Table I / Table II rows with the latest alignment applied to every stop.

No ROS here: the node converts messages and calls :meth:`add`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import numpy as np

from .. import geometry as geo
from ..errors import GeometryError
from ..fileio import atomic_write_text
from .stops import Stop, StopError, stop_errors, summarize
from .tables import write_tables
from .trajectories import MatchedPairs, align_se2, apply_se2, error_statistics, pose_errors

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ComparisonConfig:
    """Parameters of the comparison (see config/comparison.yaml for the node's documented copy).

    Attributes:
        alignment: (x m, y m, yaw rad) of the estimate's map frame in the reference's, or None to
            estimate it.
        min_pairs: pairs needed before the alignment is estimated.
        max_pairs: pairs kept for the alignment (older ones thinned).
        still_time: s the reference must stay still to record a stop automatically (<= 0: never).
        still_position_tolerance: m; still_yaw_tolerance: rad.
        settle: s ignored at the start of a still period (our filter catching up).
        record_window: s of pairs averaged by a requested stop.
    """

    alignment: Optional[Sequence[float]] = None
    min_pairs: int = 10
    max_pairs: int = 2000
    still_time: float = 3.0
    still_position_tolerance: float = 0.01
    still_yaw_tolerance: float = float(np.radians(0.5))
    settle: float = 1.0
    record_window: float = 1.0


@dataclass
class RecordedStop:
    """Raw poses of one stop (reference and estimate in their own frames)."""

    label: str
    stamps: np.ndarray
    ref: np.ndarray
    est: np.ndarray
    source: str  # "still" or "request"


class ComparisonCore:
    """Accumulates pose pairs, estimates the frame alignment, records stops (see module doc)."""

    def __init__(self, config: ComparisonConfig = ComparisonConfig()) -> None:
        self.config = config
        self._stamps: List[float] = []
        self._ref: List[np.ndarray] = []
        self._est: List[np.ndarray] = []
        self._given = None if config.alignment is None else np.asarray(config.alignment, dtype=float).reshape(3)
        self._T: Optional[np.ndarray] = None if self._given is None else self._given.copy()
        self.stops: List[RecordedStop] = []
        self._still_start: Optional[int] = None  # index of the first pose of the current still period
        self._still_recorded = False
        self.last_errors: Optional[np.ndarray] = None

    # --- input ------------------------------------------------------------------------------
    def add(self, stamp: float, ref: Sequence[float], est: Sequence[float]) -> Optional[np.ndarray]:
        """Add a time-matched pair (x, y, yaw) each; returns the live errors (4,) or None.

        Pairs going back in time (a bag loop) reset everything but the recorded stops.
        """
        r = np.asarray(ref, dtype=float).reshape(3)
        e = np.asarray(est, dtype=float).reshape(3)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(e)) and np.isfinite(stamp)):
            raise GeometryError("comparison: non-finite pose pair")
        if self._stamps and stamp < self._stamps[-1]:
            logger.warning("comparison: time went back from %.3f to %.3f s: pairs cleared", self._stamps[-1], stamp)
            self._stamps, self._ref, self._est = [], [], []
            self._still_start, self._still_recorded = None, False
        elif self._stamps and stamp == self._stamps[-1]:
            return self.last_errors
        self._stamps.append(float(stamp))
        self._ref.append(r)
        self._est.append(e)
        self._update_still()
        if self._given is None and len(self._stamps) >= self.config.min_pairs:
            self._T = self._estimate_alignment()
        if self._T is None:
            self.last_errors = None
            return None
        self.last_errors = pose_errors(r, apply_se2(self._T, e[None]))[0]
        return self.last_errors

    def _estimate_alignment(self) -> np.ndarray:
        n = len(self._stamps)
        idx = np.arange(n) if n <= self.config.max_pairs else np.linspace(0, n - 1, self.config.max_pairs).astype(int)
        est = np.asarray(self._est)[idx]
        ref = np.asarray(self._ref)[idx]
        return align_se2(est, ref)

    # --- alignment --------------------------------------------------------------------------
    @property
    def alignment(self) -> Optional[np.ndarray]:
        """(3,) (x m, y m, yaw rad): the estimate's map frame in the reference map frame, or None."""
        return None if self._T is None else self._T.copy()

    @property
    def alignment_given(self) -> bool:
        return self._given is not None

    def alignment_transform(self) -> Optional[np.ndarray]:
        """The alignment as a 4x4 ``T_refmap_estmap`` (z = 0), or None before it is known."""
        return None if self._T is None else geo.transform_from_se2(*self._T)

    @property
    def n_pairs(self) -> int:
        return len(self._stamps)

    # --- stops ------------------------------------------------------------------------------
    def _update_still(self) -> None:
        c = self.config
        if c.still_time <= 0:
            return
        k = len(self._stamps) - 1
        if self._still_start is None:
            self._still_start, self._still_recorded = k, False
            return
        r0, r = self._ref[self._still_start], self._ref[k]
        moved = (np.hypot(r[0] - r0[0], r[1] - r0[1]) > c.still_position_tolerance
                 or abs(geo.angle_diff(r[2], r0[2])) > c.still_yaw_tolerance)
        if moved:
            self._still_start, self._still_recorded = k, False
            return
        t0 = self._stamps[self._still_start]
        if not self._still_recorded and self._stamps[k] - t0 >= c.still_time:
            self._record(t0 + min(c.settle, c.still_time / 2), self._stamps[k], "still")
            self._still_recorded = True
        elif self._still_recorded and self.stops and self.stops[-1].source == "still":
            # keep extending the stop while the robot stays
            self._extend_last(k)

    def _extend_last(self, k: int) -> None:
        s = self.stops[-1]
        s.stamps = np.append(s.stamps, self._stamps[k])
        s.ref = np.vstack([s.ref, self._ref[k]])
        s.est = np.vstack([s.est, self._est[k]])

    def _record(self, start: float, end: float, source: str) -> Optional[RecordedStop]:
        s = np.asarray(self._stamps)
        inside = (s >= start) & (s <= end)
        if not np.any(inside):
            return None
        stop = RecordedStop(str(len(self.stops) + 1), s[inside], np.asarray(self._ref)[inside],
                            np.asarray(self._est)[inside], source)
        self.stops.append(stop)
        logger.info("comparison: stop %s recorded (%s, %d poses)", stop.label, source, len(stop.stamps))
        return stop

    def record_stop(self) -> Optional[RecordedStop]:
        """Record a stop now from the last ``record_window`` s of pairs; None without pairs."""
        if not self._stamps:
            return None
        end = self._stamps[-1]
        return self._record(end - self.config.record_window, end, "request")

    # --- output -----------------------------------------------------------------------------
    def stop_rows(self) -> List[StopError]:
        """One Table I/II row per recorded stop, with the current alignment applied."""
        T = self._T if self._T is not None else np.zeros(3)
        rows = []
        for s in self.stops:
            pairs = MatchedPairs(s.stamps, s.ref, apply_se2(T, s.est))
            rows += stop_errors(pairs, [Stop(float(s.stamps[0]), float(s.stamps[-1]))], labels=[s.label])
        return rows

    def statistics(self) -> Dict[str, float]:
        """Error statistics over every pair so far (with the current alignment)."""
        if self._T is None or not self._stamps:
            return {"n": 0}
        return error_statistics(pose_errors(np.asarray(self._ref), apply_se2(self._T, np.asarray(self._est))))

    def status_text(self) -> str:
        """A few lines for the rviz text marker."""
        if self._T is None:
            return f"comparison: waiting for pairs ({len(self._stamps)}/{self.config.min_pairs})"
        e = self.last_errors
        lines = []
        if e is not None:
            lines.append(f"error {100 * e[2]:.1f} cm (x {100 * e[0]:+.1f}, y {100 * e[1]:+.1f}), "
                         f"yaw {np.degrees(e[3]):+.2f} deg")
        rows = self.stop_rows()
        if rows:
            s = summarize(rows)
            lines.append(f"{len(rows)} stops: median {s['position_cm_median']:.1f} cm, max {s['position_cm_max']:.1f} cm, "
                         f"|yaw| mean {s['yaw_deg_mean_abs']:.2f} deg")
        T = self._T
        lines.append(f"alignment ({'given' if self._given is not None else 'fitted'}): "
                     f"{T[0]:+.3f} m, {T[1]:+.3f} m, {np.degrees(T[2]):+.2f} deg")
        return "\n".join(lines)

    def write(self, out_dir: str, reference_name: str = "reference") -> Dict[str, str]:
        """Write Table I/II (markdown + CSV) of the recorded stops into ``out_dir``."""
        import json
        import os

        rows = self.stop_rows()
        how = "given alignment" if self.alignment_given else "fitted alignment, which absorbs a constant offset"
        paths = write_tables(out_dir, rows, rows, reference_name=reference_name,
                             frame=f"reference's map frame ({how})")
        summary = {"pairs": self.n_pairs, "stops": summarize(rows), "all": self.statistics(),
                   "alignment": None if self._T is None else {
                       "x_m": float(self._T[0]), "y_m": float(self._T[1]), "yaw_deg": float(np.degrees(self._T[2])),
                       "given": self.alignment_given}}
        paths["summary"] = os.path.join(out_dir, "comparison_summary.json")
        atomic_write_text(paths["summary"], json.dumps(summary, indent=2) + "\n", keep_backup=False)
        return paths
