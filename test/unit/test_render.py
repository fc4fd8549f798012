"""Image mode of the ring simulator: exact ray grid, markers where the camera model projects them,
quiet zone, painter's order, seeded noise, a background without marker-like black/white blocks."""
from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.render import RingRenderer, background_panorama, ray_grid
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Plate, Room, Scene, SceneMarker, marker_pose

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="module")
def ring():
    return CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))


def _scene(markers):
    return Scene(name="t", world_frame="world", room=Room((-20.0, -20.0), (40.0, 40.0)),
                 plate=Plate((0.0, 0.0), (2.0, 2.0)), markers=markers)


def _facing_cam0(mid, x, y=0.0, z=0.75, size=0.2, turn_deg=0.0):
    return SceneMarker(mid, marker_pose([x, y, z], np.pi + np.radians(turn_deg)), size)


def _sample(img, px):
    """Bilinear grey value at pixel coordinates (N, 2)."""
    m = px.astype(np.float32).reshape(-1, 1, 2)
    return cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR).ravel().astype(float)


def test_ray_grid_matches_normalize(ring):
    model = ring["cam3"].model
    xn, yn = ray_grid(model)
    rng = np.random.default_rng(0)
    px = np.stack([rng.integers(0, model.width, 200), rng.integers(0, model.height, 200)], axis=1)
    exact = model.normalize(px.astype(float))
    got = np.stack([xn[px[:, 1], px[:, 0]], yn[px[:, 1], px[:, 0]]], axis=1)
    err_px = np.abs(got - exact).max() * model.fx
    assert err_px < 0.01, f"ray grid off by {err_px:.4f} px"


def test_marker_is_drawn_where_the_model_projects_it(ring):
    L = 0.2
    scene = _scene([_facing_cam0(7, 2.0, y=0.3, turn_deg=30.0, size=L)])
    sim = RingSimulator(scene, ring, seed=1)
    img = sim.render(np.eye(4), cameras=["cam0"])["cam0"]
    assert img.shape == (ring["cam0"].model.height, ring["cam0"].model.width) and img.dtype == np.uint8
    T_cam_marker = geo.inverse(ring["cam0"].T_base_cam) @ scene.markers[0].T_world_marker
    m = L / 7.0   # one module
    border = np.array([[-L / 2 + m / 2, t, 0.0] for t in np.linspace(-0.4, 0.4, 9) * L]
                      + [[t, L / 2 - m / 2, 0.0] for t in np.linspace(-0.4, 0.4, 9) * L])
    quiet = border.copy()
    quiet[:9, 0] = -L / 2 - m / 2
    quiet[9:, 1] = L / 2 + m / 2
    proj = lambda p: ring["cam0"].model.project(geo.transform_points(T_cam_marker, p))  # noqa: E731
    dark, bright = _sample(img, proj(border)), _sample(img, proj(quiet))
    assert dark.max() < 80, f"black border rendered at grey {dark.max():.0f}"
    assert bright.min() > 170, f"quiet zone rendered at grey {bright.min():.0f}"
    # Detected corners agree with the projection (OpenCV SUBPIX: within its known ~0.5 px inward bias).
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(7), params)
    corners, ids, _ = det.detectMarkers(img)
    assert ids is not None and ids.ravel().tolist() == [7]
    truth = sim.visible(np.eye(4))["cam0"][0][1]
    err = np.linalg.norm(corners[0].reshape(4, 2) - truth, axis=1).max()
    assert err < 0.8, f"corner error {err:.2f} px"


def test_nearer_marker_is_drawn_over_farther(ring):
    near, far = _facing_cam0(1, 2.0), _facing_cam0(2, 3.0, y=0.04)
    kw = dict(seed=3)
    both = RingSimulator(_scene([near, far]), ring, **kw).render(np.eye(4), rng=np.random.default_rng(0),
                                                                  cameras=["cam0"])["cam0"]
    only_near = RingSimulator(_scene([near]), ring, **kw).render(np.eye(4), rng=np.random.default_rng(0),
                                                                 cameras=["cam0"])["cam0"]
    # The near marker's region is identical whether or not the far one is behind it.
    c = RingSimulator(_scene([near]), ring).visible(np.eye(4))["cam0"][0][1]
    x0, y0 = np.floor(c.min(axis=0)).astype(int) + 3
    x1, y1 = np.ceil(c.max(axis=0)).astype(int) - 3
    assert np.array_equal(both[y0:y1, x0:x1], only_near[y0:y1, x0:x1])
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(7))
    _, ids, _ = det.detectMarkers(both)
    assert ids is not None and ids.ravel().tolist() == [1]


def test_render_is_seeded(ring):
    scene = Scene.default()
    pose = scene.test_positions[3]
    a = RingSimulator(scene, ring, seed=4).render(pose, rng=np.random.default_rng(1), cameras=["cam2"])["cam2"]
    b = RingSimulator(scene, ring, seed=4).render(pose, rng=np.random.default_rng(1), cameras=["cam2"])["cam2"]
    c = RingSimulator(scene, ring, seed=4).render(pose, rng=np.random.default_rng(2), cameras=["cam2"])["cam2"]
    assert np.array_equal(a, b)
    diff = np.abs(a.astype(int) - c.astype(int))
    assert 0 < diff.mean() < 5, f"different noise draws differ by {diff.mean():.2f} grey levels on average"


def test_background_has_no_black_or_white_blocks(ring):
    renderer = RingRenderer(_scene([_facing_cam0(1, 2.0)]), ring, seed=0, noise_std=0.0, blur_sigma=0.0)
    for yaw in np.radians([0, 90, 270]):
        img = renderer.render_camera(None, geo.transform_from_se2(0, 0, yaw), "cam4", np.random.default_rng(0))
        lo, hi = np.percentile(img, [0.5, 99.5])
        assert lo >= 40 and hi <= 220, (lo, hi)
        assert img.std() > 10, f"background too flat (std {img.std():.1f})"
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(7))
    _, ids, _ = det.detectMarkers(img)
    assert ids is None, ids


def test_background_turns_with_the_robot(ring):
    renderer = RingRenderer(_scene([_facing_cam0(1, 2.0)]), ring, seed=0, noise_std=0.0, blur_sigma=0.0)
    a = renderer.render_camera(None, geo.transform_from_se2(0, 0, 0.0), "cam4", np.random.default_rng(0))
    # Turning the robot left by 45 deg shows cam4 what cam5 saw before... almost: cam3's view moves to cam4.
    b = renderer.render_camera(None, geo.transform_from_se2(0, 0, np.radians(45)), "cam3", np.random.default_rng(0))
    assert np.mean(np.abs(a.astype(int) - b.astype(int))) < 3.0


def _edge_offsets(img, model, T_cam_marker, L):
    """Signed distance (px, + outward) between the rendered outer edge of the black square and its
    true projection, at 3 points per side: where the grey profile across the edge crosses the
    mean of the border (half a module inside) and quiet-zone (half a module outside) levels."""
    h, mod = L / 2.0, L / 7.0
    C = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    out = []
    for k in range(4):
        a, b = C[k], C[(k + 1) % 4]
        e = (b - a) / np.linalg.norm(b - a)
        nrm = np.array([e[1], -e[0], 0.0])
        for s in (0.35, 0.5, 0.65):
            p = a + (b - a) * s
            if nrm @ p < 0:
                nrm = -nrm
            px = model.project(geo.transform_points(T_cam_marker, np.array(
                [p, p + nrm * 1e-4, p - nrm * 0.5 * mod, p + nrm * 0.5 * mod])))
            t = (px[1] - px[0]) / np.linalg.norm(px[1] - px[0])
            mid = 0.5 * (_sample(img, px[2:3])[0] + _sample(img, px[3:4])[0])
            ds = np.linspace(-2.0, 2.0, 401)
            prof = _sample(img, px[0][None, :] + ds[:, None] * t[None, :]) - mid
            i = np.flatnonzero(prof[:-1] * prof[1:] <= 0)
            i = i[np.argmin(np.abs(ds[i]))]
            step = prof[i + 1] - prof[i]
            out.append(ds[i] if step == 0 else ds[i] - prof[i] / step * (ds[i + 1] - ds[i]))
    return np.array(out)


def test_marker_edges_are_area_sampled_at_their_true_subpixel_position(ring):
    """Unbiased edges, and no snapping to pixel boundaries: point sampling (supersample=1, the
    control) scatters them by up to half a pixel."""
    L = 0.2
    rng = np.random.default_rng(5)
    spread = {}
    for ss in (2, 1):
        offs = []
        for k in range(6):
            m = _facing_cam0(3, rng.uniform(1.5, 3.5), y=rng.uniform(-0.4, 0.4), z=rng.uniform(0.6, 0.9),
                             turn_deg=rng.uniform(-40, 40))
            scene = _scene([m])
            r = RingRenderer(scene, ring, seed=0, blur_sigma=0.0, noise_std=0.0, supersample=ss)
            img = r.render_camera(None, np.eye(4), "cam0", np.random.default_rng(0))
            T_cam_marker = geo.inverse(ring["cam0"].T_base_cam) @ m.T_world_marker
            offs.append(_edge_offsets(img, ring["cam0"].model, T_cam_marker, L))
        offs = np.concatenate(offs)
        spread[ss] = float(np.std(offs))
        if ss == 2:
            assert abs(offs.mean()) < 0.03, f"edges biased by {offs.mean():+.3f} px"
            assert spread[2] < 0.12 and np.abs(offs).max() < 0.25, \
                f"edge offsets std {spread[2]:.3f} px, max {np.abs(offs).max():.3f} px"
    assert spread[1] > 1.5 * spread[2], f"point sampling std {spread[1]:.3f} vs area sampling {spread[2]:.3f} px"


def test_background_panorama_wraps_without_a_seam():
    period, width = 3000, 640
    pano = background_panorama(200, period, width, seed=3).astype(float)
    assert pano.shape == (200, period + width)
    assert np.array_equal(pano[:, period:], pano[:, :width]), "not periodic"
    steps = np.abs(np.diff(pano[:, :period], axis=1)).mean(axis=0)     # neighbour-column differences
    wrap = float(np.abs(pano[:, 0] - pano[:, period - 1]).mean())
    assert wrap < np.percentile(steps, 99), f"wrap step {wrap:.2f} grey vs p99 column step {np.percentile(steps, 99):.2f}"
