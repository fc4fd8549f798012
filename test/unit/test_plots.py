"""Figures: each plot function writes a non-empty PNG from seeded data."""
from __future__ import annotations

import numpy as np

from aruco_ring_localization import plots


def _is_png(path) -> bool:
    with open(path, "rb") as handle:
        return handle.read(8) == b"\x89PNG\r\n\x1a\n"


def test_all_figures(tmp_path):
    rng = np.random.default_rng(5)
    plate = plots.plate_polygon((0.0, 0.0), (3.67, 2.51))
    room = plots.room_polygon((-5.5, -4.5), (11.0, 9.0))
    assert plate.shape == (4, 2) and np.allclose(plate.mean(axis=0), 0)
    T = np.eye(4)
    T[:2, 3] = (1.0, 2.0)
    assert np.allclose(plots.plate_polygon((0.0, 0.0), (2.0, 2.0), T).mean(axis=0), (1.0, 2.0))
    markers = {}
    for k in range(6):
        c = np.array([[-0.1, 0, 0.2], [0.1, 0, 0.2], [0.1, 0, 0.0], [-0.1, 0, 0.0]]) + (k - 3, 4.0, 1.0)
        markers[k] = c
    true_xy = rng.uniform(-1.5, 1.5, (15, 2))
    est_xy = true_xy + rng.normal(scale=0.005, size=(15, 2))
    yaw = np.radians(np.arange(0, 360, 45))
    cases = [{"label": f"P{k}", "true": (0.0, 0.0, 0.0), "fused": (0.003, -0.002, 0.0),
              "cameras": {f"cam{j}": tuple(rng.normal(scale=0.02, size=3)) for j in range(4)}} for k in range(3)]
    paths = [
        plots.plot_map(str(tmp_path / "map.png"), markers, markers, plate=plate, room=room, robot_pose=(0, 0, 0)),
        plots.plot_positions(str(tmp_path / "pos.png"), true_xy, est_xy, plate=plate,
                             errors_cm=100 * np.linalg.norm(est_xy - true_xy, axis=1)),
        plots.plot_camera_estimates(str(tmp_path / "cams.png"), cases),
        plots.plot_orientations(str(tmp_path / "or.png"), yaw, yaw + 0.01),
        plots.plot_trajectory(str(tmp_path / "traj.png"), np.arange(15.0), np.column_stack([true_xy, np.zeros(15)]),
                              np.column_stack([est_xy, np.zeros(15)]), plate=plate),
    ]
    for p in paths:
        size = (tmp_path / p).stat().st_size if not p.startswith("/") else __import__("os").path.getsize(p)
        assert _is_png(p) and size > 5000, f"{p}: {size} bytes"
