"""The marker map as an occupancy grid (marker_grid.py): footprints where the markers are, unknown
elsewhere, OccupancyGrid's layout (row = y, column = x, from the origin cell)."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.marker_grid import OCCUPIED, UNKNOWN, marker_grid
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap


def _map() -> MarkerMap:
    floor = MarkerEntry(1, geo.make_transform(t=[1.0, 2.0, 0.0]), 0.2)                     # flat on the floor
    wall = MarkerEntry(2, geo.make_transform(geo.matrix_from_rpy(np.pi / 2, 0, 0), [4.0, 5.0, 1.0]), 0.4)  # facing -y
    return MarkerMap([floor, wall], frame_id="map")


def test_floor_marker_is_a_square_wall_marker_a_line_the_rest_unknown():
    grid = marker_grid(_map(), resolution=0.05, margin=0.5)
    assert grid.data.dtype == np.int8
    assert set(np.unique(grid.data)) == {OCCUPIED, UNKNOWN}
    # the floor marker: its 0.2 m square is 4 x 4 cells (5 with the closing edge)
    r, c = grid.cell_of(1.0, 2.0)
    block = grid.data[r - 1:r + 2, c - 1:c + 2]
    assert (block == OCCUPIED).all()
    assert grid.data[grid.cell_of(1.0, 2.3)] == UNKNOWN and grid.data[grid.cell_of(1.3, 2.0)] == UNKNOWN
    # the wall marker (x axis along map x, normal along -y): a 0.4 m line at y = 5
    for x in (3.82, 4.0, 4.18):
        assert grid.data[grid.cell_of(x, 5.0)] == OCCUPIED
    assert grid.data[grid.cell_of(4.0, 5.1)] == UNKNOWN and grid.data[grid.cell_of(4.3, 5.0)] == UNKNOWN
    floor_cells = np.count_nonzero(grid.data == OCCUPIED)
    assert 16 + 8 <= floor_cells <= 25 + 10, floor_cells  # one square and one line, nothing else


def test_extent_is_the_markers_box_plus_margin():
    grid = marker_grid(_map(), resolution=0.1, margin=1.0)
    # corners: x from 0.9 to 4.2, y from 1.9 to 5.0 (the wall marker is edge-on)
    assert grid.origin == pytest.approx((-0.1, 0.9))
    assert grid.resolution == pytest.approx(0.1, rel=1e-7)
    assert grid.width == int(np.ceil((4.2 + 1.0 - (-0.1)) / grid.resolution - 1e-6))
    assert grid.height == int(np.ceil((5.0 + 1.0 - 0.9) / grid.resolution - 1e-6))


def test_empty_map_and_bad_arguments():
    grid = marker_grid(MarkerMap([], frame_id="map"))
    assert grid.data.shape == (1, 1) and grid.data[0, 0] == UNKNOWN
    for kwargs, field in (({"resolution": 0.0}, "resolution"), ({"resolution": float("nan")}, "resolution"),
                          ({"margin": -1.0}, "margin")):
        with pytest.raises(ValueError, match=field):
            marker_grid(_map(), **kwargs)


def test_a_huge_map_is_drawn_coarser_not_allocated_whole():
    far = MarkerMap([MarkerEntry(1, geo.make_transform(t=[0, 0, 0]), 0.2),
                     MarkerEntry(2, geo.make_transform(t=[4000.0, 4000.0, 0]), 0.2)], frame_id="map")
    grid = marker_grid(far, resolution=0.05)
    assert grid.data.size <= 2048 * 2048
    assert grid.resolution > 0.05
    assert grid.data[grid.cell_of(0.0, 0.0)] == OCCUPIED and grid.data[grid.cell_of(4000.0, 4000.0)] == OCCUPIED


def test_cells_agree_with_a_reader_of_the_float32_resolution():
    """OccupancyGrid carries the resolution as float32: a marker centre on a cell boundary in float64
    arithmetic (x = 0 with the origin at -0.5 m) must land in the cell a reader computes."""
    m = MarkerMap([MarkerEntry(1, geo.make_transform(geo.matrix_from_rpy(np.pi / 2, 0, np.pi / 2), [0.0, 3.1, 1.1]), 0.2)],
                  frame_id="map")
    grid = marker_grid(m, resolution=0.05, margin=0.5)
    res = float(np.float32(grid.resolution))
    assert res == grid.resolution
    col = int((0.0 - grid.origin[0]) // res)
    row = int((3.1 - grid.origin[1]) // res)
    assert grid.data[row, col] == OCCUPIED


def test_an_oblique_wall_marker_covers_every_cell_its_line_crosses():
    """An edge-on marker at 51 deg: each point along it (its centre too) is in an occupied cell."""
    yaw = np.radians(51.0)
    R = geo.rot_z(yaw) @ geo.matrix_from_rpy(np.pi / 2, 0, 0)
    e = MarkerEntry(64, geo.make_transform(R, [2.45, 2.04, 0.7]), 0.2)
    grid = marker_grid(MarkerMap([e], frame_id="map"), resolution=0.05, margin=0.5)
    c = e.corners_in_map()[:, :2]
    for s in np.linspace(0.0, 1.0, 41):
        p = c[0] + s * (c[1] - c[0])
        assert grid.data[grid.cell_of(*p)] == OCCUPIED, (s, p)
    assert grid.data[grid.cell_of(2.45, 2.04)] == OCCUPIED
