"""The marker map as a 2D occupancy grid, for map_server-style users (nav_msgs/OccupancyGrid).

The YAML marker map (docs/formats.md) is the map the localizer uses; this is a picture of it for
tools that expect a grid (rviz's Map display, map_server's ``static_map`` service type
nav_msgs/GetMap, a costmap's static layer fed by hand): every cell under a marker's footprint
(its four corners projected onto the floor plane: a square for a floor or ceiling marker, a line
for a wall marker) is 100 (occupied), every other cell -1 (unknown). The grid says where the
markers are and nothing about free space: the marker map does not know it.

The grid covers the markers' bounding box plus ``margin`` on each side, ``resolution`` m per cell,
row-major from the cell at ``origin`` (x to the right, y up: OccupancyGrid's layout).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import cv2
import numpy as np

from .marker_map import MarkerMap

OCCUPIED = 100
UNKNOWN = -1
DEFAULT_RESOLUTION = 0.05   # m per cell, map_server's usual 5 cm
DEFAULT_MARGIN = 0.5        # m of unknown around the markers
MAX_CELLS = 2048 * 2048     # a 100 m x 100 m map at 5 cm (4 MB); a larger one is drawn coarser


@dataclass(frozen=True)
class MarkerGrid:
    """An occupancy grid: ``data[row, col]`` is the cell at ``origin + (col, row) * resolution``."""

    data: np.ndarray          # (height, width) int8, OCCUPIED or UNKNOWN
    resolution: float         # m per cell
    origin: Tuple[float, float]  # map-frame (x, y) of cell (0, 0)'s corner

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    def cell_of(self, x: float, y: float) -> Tuple[int, int]:
        """(row, col) of the cell holding map point (x, y)."""
        return (int(np.floor((y - self.origin[1]) / self.resolution)),
                int(np.floor((x - self.origin[0]) / self.resolution)))


def marker_grid(marker_map: MarkerMap, resolution: float = DEFAULT_RESOLUTION,
                margin: float = DEFAULT_MARGIN) -> MarkerGrid:
    """Draws every marker's floor-plane footprint into a grid (module docstring).

    Raises:
        ValueError: resolution or margin not positive / finite.
    """
    if not (np.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution: must be > 0 m, got {resolution!r}")
    if not (np.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin: must be >= 0 m, got {margin!r}")
    footprints = [e.corners_in_map()[:, :2] for e in marker_map]
    if not footprints:
        return MarkerGrid(np.full((1, 1), UNKNOWN, np.int8), float(resolution), (-resolution / 2, -resolution / 2))
    pts = np.concatenate(footprints)
    lo = pts.min(axis=0) - margin
    hi = pts.max(axis=0) + margin
    size = hi - lo
    cells = float(np.prod(np.ceil(size / resolution)))
    if cells > MAX_CELLS:
        resolution = float(resolution * np.sqrt(cells / MAX_CELLS) * 1.001)
    # OccupancyGrid's resolution is a float32: draw with that value, so a reader's cells are ours
    resolution = float(np.float32(resolution))
    width, height = (int(v) for v in np.maximum(np.ceil(size / resolution), 1))
    data = np.full((height, width), UNKNOWN, np.int8)
    for quad in footprints:
        q = (quad - lo) / resolution                       # corners in cell units, (col, row) = cv2's (x, y)
        cv2.fillConvexPoly(data, cv2.convexHull(np.floor(q).astype(np.int32)), OCCUPIED)
        # every cell the outline passes through (an edge-on wall marker is only its outline): the
        # edges sampled at a quarter cell, so no cell a segment crosses is skipped
        for a, b in zip(q, np.roll(q, -1, axis=0)):
            n = int(np.ceil(np.linalg.norm(b - a) * 4)) + 1
            pts = np.floor(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)).astype(np.int64)
            cols = np.clip(pts[:, 0], 0, width - 1)
            rows = np.clip(pts[:, 1], 0, height - 1)
            data[rows, cols] = OCCUPIED
    return MarkerGrid(data, float(resolution), (float(lo[0]), float(lo[1])))
