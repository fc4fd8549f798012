"""A planar laser scanner in the simulated hall: ranges to the walls and posts (:class:`LaserScanner`).

The scan plane is horizontal at the scanner; beams go counter-clockwise from ``angle_min`` to
``angle_max`` around the scanner's x axis (sensor_msgs/LaserScan conventions). Ranges beyond
``range_max`` (nothing hit) are reported as ``inf`` (REP-117).
"""
from __future__ import annotations

import logging
from typing import Optional, Sequence

import numpy as np

from .params import LaserParams

logger = logging.getLogger(__name__)


class LaserScanner:
    """Ray casting against 2D segments.

    Args:
        segments: (N, 2, 2) obstacle segments [[x0, y0], [x1, y1]] in the world (``Scene.obstacle_segments``).
        beams: number of beams.
        angle_min, angle_max: first and last beam angle, rad, in the scanner frame.
        range_min, range_max: valid range, m.
        noise_std: Gaussian range noise, m.
        seed: seed of the noise.
    """

    def __init__(self, segments: np.ndarray, beams: int = LaserParams.beams, angle_min: float = -np.pi,
                 angle_max: Optional[float] = None, range_min: float = 0.05, range_max: float = LaserParams.range_max,
                 noise_std: float = 0.01, seed: int = 0):
        self.segments = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
        self.beams = int(beams)
        self.angle_min = float(angle_min)
        self.angle_max = float(angle_max) if angle_max is not None else \
            float(angle_min + 2 * np.pi * (beams - 1) / beams)
        self.angle_increment = (self.angle_max - self.angle_min) / max(self.beams - 1, 1)
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        self.noise_std = float(noise_std)
        self.rng = np.random.default_rng([int(seed), 0x1a5])

    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(self.beams)

    def scan(self, pose: Sequence[float]) -> np.ndarray:
        """Ranges (beams,) in m from the scanner at world pose (x, y, yaw); ``inf`` where nothing is hit."""
        x, y, yaw = (float(v) for v in pose)
        a = self.angles() + yaw
        d = np.stack([np.cos(a), np.sin(a)], axis=1)                 # (B, 2)
        p0 = self.segments[:, 0, :] - (x, y)                          # (N, 2)
        e = self.segments[:, 1, :] - self.segments[:, 0, :]           # (N, 2)
        # Solve t d = p0 + s e  ->  cross products (2D).
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]     # (B, N)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (p0[None, :, 0] * e[None, :, 1] - p0[None, :, 1] * e[None, :, 0]) / denom
            s = (p0[None, :, 0] * d[:, None, 1] - p0[None, :, 1] * d[:, None, 0]) / denom
        hit = (np.abs(denom) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        t = np.where(hit, t, np.inf)
        r = t.min(axis=1)
        if self.noise_std > 0:
            r = r + self.rng.normal(0.0, self.noise_std, r.shape)
        r[(r > self.range_max) | ~np.isfinite(r)] = np.inf
        r[r < self.range_min] = self.range_min
        return r


def occupancy_grid(segments: np.ndarray, resolution: float, margin: float = 0.5):
    """The cells the segments (the walls and posts a laser sees) pass through, as gmapping's grid.

    Returns ``(cells, origin)``: ``cells`` (rows = y, columns = x) int8 with 100 where a segment
    passes (occupied), 0 elsewhere in the segments' bounding box (free: the room is known) and
    ``origin`` (x, y) of cell (0, 0)'s corner, m; the box grows by ``margin`` m on each side, where
    cells are -1 (unknown), as outside gmapping's walls. nav_msgs/OccupancyGrid's layout.
    """
    seg = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    lo, hi = seg.reshape(-1, 2).min(axis=0), seg.reshape(-1, 2).max(axis=0)
    origin = lo - margin
    shape = np.ceil((hi - lo + 2 * margin) / resolution).astype(int) + 1     # (nx, ny)
    cells = np.full((shape[1], shape[0]), -1, dtype=np.int8)
    inside = np.floor((np.array([lo, hi]) - origin) / resolution).astype(int)
    cells[inside[0, 1]:inside[1, 1] + 1, inside[0, 0]:inside[1, 0] + 1] = 0
    for p, q in seg:
        n = int(np.ceil(np.linalg.norm(q - p) / (0.5 * resolution))) + 1
        pts = p + np.linspace(0.0, 1.0, n)[:, None] * (q - p)
        ij = np.floor((pts - origin) / resolution).astype(int)
        cells[ij[:, 1], ij[:, 0]] = 100
    return cells, origin
