"""Planar laser of the simulated hall: ranges to walls and posts, beam geometry, range limits, seeding."""
from __future__ import annotations

import numpy as np

from aruco_ring_localization.simulation.laser import LaserScanner
from aruco_ring_localization.simulation.scene import Scene


def _box(x0, y0, x1, y1):
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


def test_beam_geometry_follows_laserscan_conventions():
    laser = LaserScanner(_box(-1, -1, 1, 1), beams=360)
    a = laser.angles()
    assert a.size == 360 and np.isclose(a[0], -np.pi) and np.isclose(laser.angle_increment, np.radians(1.0))
    assert np.isclose(laser.angle_max, a[-1]), "angle_max must be the last beam's angle"


def test_ranges_to_the_walls_of_a_square_room_from_an_off_centre_pose():
    laser = LaserScanner(_box(0, 0, 4, 2), beams=8, angle_min=0.0, noise_std=0.0)
    r = laser.scan((1.0, 0.5, 0.0))
    # Beams at 0, 45, 90, ... deg from (1, 0.5): east wall 3 m, north wall 1.5 m, west 1 m, south 0.5 m.
    assert np.allclose(r[[0, 2, 4, 6]], [3.0, 1.5, 1.0, 0.5]), r
    assert np.isclose(r[1], 1.5 * np.sqrt(2)), r[1]
    # Turning the scanner by 90 deg shifts the beams by two places (ranges are in the scanner frame).
    assert np.allclose(laser.scan((1.0, 0.5, np.pi / 2)), np.roll(r, -2))


def test_posts_shadow_the_wall_behind_them():
    scene = Scene.default()
    post = scene.posts[0]
    laser = LaserScanner(scene.obstacle_segments(), beams=720, noise_std=0.0)
    x, y = post.centre[0] - 1.0, post.centre[1]          # 1 m west of the post, looking east
    r = laser.scan((x, y, 0.0))
    ahead = int(np.argmin(np.abs(laser.angles())))
    assert np.isclose(r[ahead], 1.0 - post.side / 2, atol=1e-9), f"range to the post {r[ahead]:.4f} m"
    walls_only = LaserScanner(scene.room.wall_segments(), beams=720, noise_std=0.0).scan((x, y, 0.0))
    assert walls_only[ahead] > 2.0, walls_only[ahead]


def test_nothing_within_range_is_inf_and_noise_is_seeded():
    far = LaserScanner(_box(-50, -50, 50, 50), beams=90, range_max=20.0, noise_std=0.0).scan((0, 0, 0))
    assert np.all(np.isinf(far)), "beams beyond range_max must be inf (REP-117)"
    a = LaserScanner(_box(-2, -2, 2, 2), beams=90, noise_std=0.01, seed=4).scan((0, 0, 0))
    b = LaserScanner(_box(-2, -2, 2, 2), beams=90, noise_std=0.01, seed=4).scan((0, 0, 0))
    c = LaserScanner(_box(-2, -2, 2, 2), beams=90, noise_std=0.01, seed=5).scan((0, 0, 0))
    exact = LaserScanner(_box(-2, -2, 2, 2), beams=90, noise_std=0.0).scan((0, 0, 0))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert 0.005 < np.std(a - exact) < 0.015, f"range noise std {np.std(a - exact):.4f} m"


def test_occupancy_grid_marks_the_walls_and_knows_the_room():
    from aruco_ring_localization.simulation.laser import occupancy_grid

    cells, origin = occupancy_grid(_box(0, 0, 4, 2), 0.1, margin=0.5)
    assert np.allclose(origin, [-0.5, -0.5])
    assert cells.shape == (31, 51), cells.shape             # rows = y (2 m + 2 x 0.5 m), columns = x

    def at(x, y):
        return cells[int((y - origin[1]) / 0.1), int((x - origin[0]) / 0.1)]

    assert at(0.0, 1.0) == 100 and at(4.0, 1.0) == 100 and at(2.0, 0.0) == 100 and at(2.0, 2.0) == 100
    assert at(2.0, 1.0) == 0 and at(1.0, 0.5) == 0, "inside the room is free"
    assert at(-0.3, 1.0) == -1 and at(2.0, 2.4) == -1, "outside the walls is unknown"
    assert set(np.unique(cells)) == {-1, 0, 100}
