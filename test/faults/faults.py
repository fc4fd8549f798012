"""Fault injection for the ring's detections (used by test/integration/faults_*_rostest.py).

Pure functions on :class:`detections.RingFrame` (no rospy), each seeded through the caller's
``numpy.random.Generator``:

* :func:`silence` — drop cameras from a frame (a camera unplugged: no message at all).
* :func:`corrupt` — replace a fraction of detections by wrong ones: an id swapped to another
  mapped id, the corners of the other IPPE solution (the mirror pose that explains the same
  square almost as well), or a random quad carrying a mapped id. Returns what it did, per kind.
* :class:`FaultSchedule` — which faults are active at a given time of the run.

Message faults (silence, corruption, a missing camera_info, a frame_id without tf) are applied
by :class:`fault_relay.FaultRelay` to the simulator node's messages in flight, by stamp, so each
is exactly timed in simulated time; physical events (a kidnap, the clock jumping back) are the
simulator node's hooks (``sim/teleport``, ``sim/time_jump``), triggered by
:class:`fault_session.FaultSession` when the phase that names them starts.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.detections import CameraFrame, MarkerObservation, RingFrame
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.pnp import solve_marker_ippe
from aruco_ring_localization.ring import CameraRing

CORRUPTIONS = ("swap_id", "flip_ippe", "random_quad")


def silence(frame: RingFrame, cameras: Sequence[str]) -> RingFrame:
    """A copy of ``frame`` without ``cameras`` (as if they published nothing)."""
    return RingFrame(frame.stamp, {k: v for k, v in frame.cameras.items() if k not in set(cameras)},
                     sorted(set(frame.missing) | set(cameras)))


def _flip_ippe(obs: MarkerObservation, size: float, model) -> Optional[np.ndarray]:
    """Corners of the second IPPE solution reprojected (None when there is only one)."""
    try:
        cand = solve_marker_ippe(obs.corners, size, model)
    except Exception:  # noqa: BLE001 - a fault injector must not care why a solve failed
        return None
    if len(cand.poses) < 2:
        return None
    pts = geo.transform_points(cand.poses[1], marker_corners(size))
    px = model.project(pts)
    return px if np.all(np.isfinite(px)) else None


def _random_quad(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    cx, cy = rng.uniform(100, width - 100), rng.uniform(100, height - 100)
    r = rng.uniform(15, 80)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 4))
    # clockwise in the image like a real detection, random size and shape
    return np.stack([cx + r * np.cos(-angles), cy + r * np.sin(-angles)], axis=1)


def corrupt(frame: RingFrame, ring: CameraRing, mapped_ids: Sequence[int], sizes: Dict[int, float],
            rate: float, rng: np.random.Generator) -> Tuple[RingFrame, Dict[str, int]]:
    """Replace each detection, with probability ``rate``, by a wrong one (kind chosen uniformly).

    Returns the faulty frame and the count of injected faults per kind.
    """
    counts = {k: 0 for k in CORRUPTIONS}
    out = RingFrame(frame.stamp, {}, list(frame.missing))
    for name, cf in frame.cameras.items():
        model = cf.model or ring[name].model
        obs_out: List[MarkerObservation] = []
        present = {o.marker_id for o in cf.observations}
        for o in cf.observations:
            if rng.random() >= rate:
                obs_out.append(o)
                continue
            kind = CORRUPTIONS[int(rng.integers(len(CORRUPTIONS)))]
            if kind == "swap_id":
                others = [i for i in mapped_ids if i not in present]
                if others:
                    new_id = int(others[int(rng.integers(len(others)))])
                    obs_out.append(MarkerObservation(new_id, o.corners.copy()))
                    counts[kind] += 1
                    continue
                kind = "random_quad"
            if kind == "flip_ippe":
                flipped = _flip_ippe(o, sizes.get(o.marker_id, 0.2), model)
                if flipped is not None:
                    obs_out.append(MarkerObservation(o.marker_id, flipped))
                    counts[kind] += 1
                    continue
                kind = "random_quad"
            obs_out.append(MarkerObservation(o.marker_id, _random_quad(rng, model.width, model.height)))
            counts["random_quad"] += 1
        out.cameras[name] = CameraFrame(name, cf.stamp, obs_out, cf.model)
    return out, counts


@dataclass
class Phase:
    """One phase of a fault schedule: from ``start`` (s of the run) for ``duration`` (s).

    Message faults hold for the whole phase: cameras ``silent`` (nothing published), a fraction
    ``corrupt_rate`` of detections replaced by wrong ones, cameras with ``no_camera_info``, cameras
    whose detections carry a frame_id with no tf (``wrong_frame``). Events happen once, when the
    phase starts: ``kidnap`` (dx, dy, dyaw) carries the robot that far (world frame), and
    ``time_jump`` (s) moves the simulated clock (negative: back, as when a bag loops).
    """

    name: str
    start: float
    duration: float
    silent: Tuple[str, ...] = ()
    corrupt_rate: float = 0.0
    no_camera_info: Tuple[str, ...] = ()
    wrong_frame: Tuple[str, ...] = ()
    kidnap: Optional[Tuple[float, float, float]] = None
    time_jump: float = 0.0

    @property
    def end(self) -> float:
        return self.start + self.duration


@dataclass
class FaultSchedule:
    """Consecutive phases; :meth:`at` returns the phase active at time ``t`` (s from the start)."""

    phases: List[Phase] = field(default_factory=list)

    def add(self, name: str, duration: float, **kw) -> Phase:
        start = self.phases[-1].end if self.phases else 0.0
        p = Phase(name, start, duration, **kw)
        self.phases.append(p)
        return p

    @property
    def duration(self) -> float:
        return self.phases[-1].end if self.phases else 0.0

    def at(self, t: float) -> Phase:
        """The phase at time ``t``: the first before the run starts, the last after it ends."""
        for p in self.phases:
            if p.start <= t < p.end:
                return p
        return self.phases[0] if t < self.phases[0].start else self.phases[-1]

    def phase(self, name: str) -> Phase:
        return next(p for p in self.phases if p.name == name)

    def move_start(self, name: str, start: float) -> None:
        """Start phase ``name`` at ``start`` instead (the previous phase ends there): where its
        event really happened, one frame after it was asked for at the earliest."""
        k = next(i for i, p in enumerate(self.phases) if p.name == name)
        p = self.phases[k]
        if k > 0:
            self.phases[k - 1].duration = start - self.phases[k - 1].start
        p.duration, p.start = p.end - start, start
