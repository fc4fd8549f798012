"""evaluation.figures: every figure writes a PNG; Fig. 9 shares one scale, Fig. 10 shows small errors."""
from __future__ import annotations

import numpy as np

from aruco_ring_localization.evaluation import figures


def _is_png(path) -> bool:
    with open(path, "rb") as handle:
        return handle.read(8) == b"\x89PNG\r\n\x1a\n"


def _capture(monkeypatch):
    """Keep the figures the plot functions save, to inspect their axes."""
    saved = []
    real = figures._save

    def keep(fig, path):
        saved.append(fig)
        fig.canvas.draw()  # lay out now, as savefig does
        return real(fig, path)

    monkeypatch.setattr(figures, "_save", keep)
    return saved


def test_all_figures(tmp_path):
    rng = np.random.default_rng(5)
    plate = figures.plate_polygon((0.0, 0.0), (3.67, 2.51))
    room = figures.room_polygon((-5.5, -4.5), (11.0, 9.0))
    assert plate.shape == (4, 2) and np.allclose(plate.mean(axis=0), 0)
    T = np.eye(4)
    T[:2, 3] = (1.0, 2.0)
    assert np.allclose(figures.plate_polygon((0.0, 0.0), (2.0, 2.0), T).mean(axis=0), (1.0, 2.0))
    markers = {}
    for k in range(6):
        markers[k] = np.array([[-0.1, 0, 0.2], [0.1, 0, 0.2], [0.1, 0, 0.0], [-0.1, 0, 0.0]]) + (k - 3, 4.0, 1.0)
    true_xy = rng.uniform(-1.5, 1.5, (15, 2))
    est_xy = true_xy + rng.normal(scale=0.005, size=(15, 2))
    yaw = np.radians(np.arange(0, 360, 45))
    cases = [{"label": f"P{k}", "true": (0.0, 0.0, 0.0), "fused": (0.003, -0.002, 0.0),
              "cameras": {f"cam{j}": tuple(rng.normal(scale=0.02, size=3)) for j in range(4)}} for k in range(3)]
    paths = [
        figures.plot_map(str(tmp_path / "map.png"), markers, markers, plate=plate, room=room, robot_pose=(0, 0, 0)),
        figures.plot_positions(str(tmp_path / "pos.png"), true_xy, est_xy, plate=plate,
                               errors_cm=100 * np.linalg.norm(est_xy - true_xy, axis=1)),
        figures.plot_camera_estimates(str(tmp_path / "cams.png"), cases),
        figures.plot_orientations(str(tmp_path / "or.png"), yaw, yaw + 0.01),
        figures.plot_trajectory(str(tmp_path / "traj.png"), np.arange(15.0), np.column_stack([true_xy, np.zeros(15)]),
                                np.column_stack([est_xy, np.zeros(15)]), plate=plate),
    ]
    for p in paths:
        size = (tmp_path / p).stat().st_size
        assert _is_png(p) and size > 5000, f"{p}: {size} bytes"


def test_fig9_panels_share_one_scale_and_name_cameras_in_a_legend(tmp_path, monkeypatch):
    saved = _capture(monkeypatch)
    cases = [{"label": "near", "true": (0.0, 0.0, 0.0), "fused": (0.002, 0.0, 0.0),
              "cameras": {"c0": (0.004, 0.001, 0.0), "c1": (0.0, -0.003, 0.0)}},
             {"label": "far", "true": (2.0, 1.0, 0.0), "fused": (2.01, 1.0, 0.0),
              "cameras": {"c0": (2.08, 1.02, 0.0), "c2": (1.97, 0.95, 0.0)}}]
    figures.plot_camera_estimates(str(tmp_path / "fig9.png"), cases)
    fig = saved[-1]
    panels = [ax for ax in fig.axes if ax.get_title()]
    assert len(panels) == 2
    assert panels[0].get_xlim() == panels[1].get_xlim() and panels[0].get_ylim() == panels[1].get_ylim()
    assert panels[0].get_xlim()[1] >= 8.0, "the scale must hold the farthest estimate (8 cm)"
    assert all(not ax.texts for ax in panels), "no per-point labels (they overprint)"
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels.count("camera c0") == 1 and "camera c1" in labels and "camera c2" in labels, labels


def test_fig10_magnifies_small_heading_errors(tmp_path, monkeypatch):
    assert figures.heading_magnification(0.25) == 50
    assert figures.heading_magnification(30.0) == 1
    assert figures.heading_magnification(3.0) == 5
    saved = _capture(monkeypatch)
    yaw = np.radians(np.arange(0, 360, 45))
    figures.plot_orientations(str(tmp_path / "fig10.png"), yaw, yaw - np.radians(0.25))
    left, right = saved[-1].axes
    assert "magnified x50" in left.get_title(), left.get_title()
    # the drawn estimate is 50 x 0.25 = 12.5 deg off the true heading
    tips = [a.xy for a in left.texts if getattr(a, "arrow_patch", None) is not None][1::2]
    angle = np.degrees(np.arctan2(tips[0][1], tips[0][0]))
    assert abs(angle + 12.5) < 1e-6, angle
    assert any(t.get_text() == "-0.250" for t in right.texts)
