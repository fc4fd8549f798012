"""The harsh lab's models (simulation/conditions.py, occluding posts, motion blur) and the lab files."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import with_overrides
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.conditions import Floor, Photometry, RingVibration, apply_photometry
from aruco_ring_localization.simulation.params import PlateParams, RenderParams, RingParams, lab_config
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Post, Scene, resolve_scene_file
from aruco_ring_localization.simulation.simulator import SimulatorCore

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="module")
def ring():
    return CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))


def _slope_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))


def test_a_flat_floor_is_the_planar_pose():
    f = Floor(PlateParams(), (5.5, 4.5))
    assert np.array_equal(f.T_world_base((5.0, 4.0, 0.3)), geo.transform_from_se2(5.0, 4.0, 0.3))


def test_a_tilted_floor_rolls_and_pitches_the_robot_within_the_slope():
    f = Floor(PlateParams(tilt_deg=0.3, tilt_direction_deg=0.0), (5.5, 4.5))
    # rising toward +x: facing +x the nose is up (negative pitch), no roll; facing +y it rolls right side up
    r, p, y = geo.rpy_from_matrix(f.T_world_base((5.5, 4.5, 0.0)))
    assert p == pytest.approx(-np.radians(0.3), abs=1e-6) and abs(r) < 1e-9 and y == pytest.approx(0.0)
    r, p, y = geo.rpy_from_matrix(f.T_world_base((5.5, 4.5, np.pi / 2)))
    assert r == pytest.approx(-np.radians(0.3), abs=1e-6) and abs(p) < 1e-6 and y == pytest.approx(np.pi / 2)
    # base_link is on the floor: 1 m east of the centre it is tan(0.3 deg) higher
    assert f.T_world_base((6.5, 4.5, 1.0))[2, 3] == pytest.approx(np.tan(np.radians(0.3)), rel=1e-6)


def test_bumps_stay_within_their_slope_and_the_yaw_is_kept():
    f = Floor(PlateParams(tilt_deg=0.3, tilt_direction_deg=30.0, bump_deg=0.2, bump_wavelength=1.5), (5.5, 4.5),
              seed=4)
    rng = np.random.default_rng(0)
    slopes, heights = [], []
    for _ in range(500):
        pose = (rng.uniform(4.0, 7.0), rng.uniform(3.5, 5.5), rng.uniform(-np.pi, np.pi))
        T = f.T_world_base(pose)
        slopes.append(_slope_deg(T))
        heights.append(T[2, 3])
        assert geo.se2_from_transform(T)[2] == pytest.approx(pose[2], abs=1e-4)
        assert np.allclose(T[:2, 3], pose[:2])
    assert max(slopes) <= 0.5 + 1e-6 and np.ptp(slopes) > 0.1, (min(slopes), max(slopes))
    assert np.ptp(heights) > 0.005


def test_vibration_draws_fresh_small_rotations_each_frame():
    v = RingVibration(RingParams(vibration_rot_std_deg=0.05, vibration_trans_std=0.0001), seed=1)
    angles, moves = [], []
    for _ in range(300):
        for D in v.draw(["a", "b"]).values():
            angles.append(np.degrees(geo.rvec_from_rotation(D[:3, :3])))
            moves.append(D[:3, 3])
    assert np.std(np.array(angles)) == pytest.approx(0.05, rel=0.1)
    assert np.std(np.array(moves)) == pytest.approx(0.0001, rel=0.1)
    rigid = RingVibration(RingParams())
    assert rigid.rigid and all(np.array_equal(D, np.eye(4)) for D in rigid.draw(["a"]).values())


def test_a_shaken_base_moves_the_camera_by_the_vibration(ring):
    cam = ring.cameras[0]
    T = geo.transform_from_se2(5.0, 4.0, 0.4)
    D = np.eye(4)
    D[:3, :3] = geo.rotation_from_rvec(np.radians([0.05, -0.03, 0.02]))
    T2 = RingVibration.shaken_base(T, cam.T_base_cam, D)
    assert np.allclose(T2 @ cam.T_base_cam, T @ cam.T_base_cam @ D)


def test_photometry_gain_wanders_and_the_gradient_is_bounded():
    ph = Photometry(RenderParams(gain_std=0.25, illumination_gradient=0.3), ["a"], rate=10.0, seed=3)
    gains = [ph.draw()["a"][0] for _ in range(2000)]
    assert np.std(np.log(gains)) == pytest.approx(0.25, rel=0.3)
    assert abs(np.log(gains[1] / gains[0])) < 0.2        # correlated from frame to frame
    flat = np.full((96, 128), 100.0, np.float32)
    out = apply_photometry(flat, (1.0, 0.3, 0.0))
    assert out.dtype == np.uint8 and out[:, 0].mean() == pytest.approx(100 * (1 - 0.3 / np.sqrt(2)), abs=2.0)
    assert out[:, -1].mean() == pytest.approx(100 * (1 + 0.3 / np.sqrt(2)), abs=2.0)
    assert apply_photometry(flat, (3.0, 0.0, 0.0)).max() == 255   # saturates
    assert Photometry(RenderParams(), ["a"]).draw() == {"a": None}


def test_a_post_ray_test():
    post = Post("p", (2.0, 0.0), 0.4, 2.0, occludes=True)
    o = np.zeros(3)
    d = np.array([[1.0, 0.0, 0.5], [1.0, 0.0, 2.0], [1.0, 1.0, 0.0], [-1.0, 0.0, 0.5], [1.0, 0.0, 0.0]])
    t = post.ray_hits(np.array([0.0, 0.0, 0.5]), d)
    assert t[0] == pytest.approx(1.8) and np.isinf(t[2]) and np.isinf(t[3]) and t[4] == pytest.approx(1.8)
    assert np.isinf(t[1])   # steep ray: above the post when it gets there
    assert np.isinf(post.ray_hits(o, d[:1], t_max=1.0))[0]   # the segment ends before the post


def _pillar_scene(occludes: bool) -> Scene:
    """The lab with a pillar between the plate centre and marker 42 (east wall)."""
    scene = Scene.default()
    m = scene.marker(42)
    centre = scene.plate.centre
    x, y = 0.5 * (centre[0] + m.T_world_marker[0, 3]), 0.5 * (centre[1] + m.T_world_marker[1, 3])
    scene.posts = list(scene.posts) + [Post("pillar", (x, y), 0.4, 3.0, occludes=occludes)]
    return scene


def test_an_occluding_post_hides_the_marker_behind_it_in_both_modes(ring):
    pose = Scene.default().mapping_pose
    T = Scene.T_world_base(pose)
    seen = {}
    for occ in (False, True):
        sim = RingSimulator(_pillar_scene(occ), ring, pixel_noise=0.0, render=RenderParams(noise_std=0.0))
        seen[occ] = {c: [i for i, _ in v] for c, v in sim.visible(T).items()}
        images = sim.render(T)
        cam = next(c for c, ids in seen[False].items() if 42 in ids)
        if occ:
            from aruco_ring_localization.detection import Detector, DetectorParams
            det = Detector(DetectorParams(dictionary=sim.scene.dictionary))
            assert 42 not in [o.marker_id for o in det.detect(images[cam])]
            assert 42 not in seen[True][cam]
            # the pillar is drawn: grey pixels where the marker was
            px = dict(RingSimulator(_pillar_scene(False), ring).visible(T)[cam])[42].mean(axis=0).astype(int)
            assert 80 <= images[cam][px[1], px[0]] <= 140
    others = {c: [i for i in ids if i != 42] for c, ids in seen[False].items()}
    assert {c: [i for i in ids if i != 42] for c, ids in seen[True].items()} == others


def test_the_harsh_lab_core_blurs_while_driving_and_not_at_rest(ring):
    cfg = with_overrides(lab_config("harsh"), {"mode": "images", "robot.waypoints": "test_positions",
                                               "robot.limits.max_speed": 0.5, "cameras.names": ("cam0",)})
    core = SimulatorCore(cfg, Scene.load(resolve_scene_file(cfg.scene.file)), ring)
    assert core.scene.occluders and core.config.cameras.trigger == "free"
    t, views_moving, views_still = 1.0, 0, 0
    for _ in range(120):
        t += 0.1
        state = core.step(t, 0.1)
        views = core.exposure_views("cam0")
        moving = np.hypot(*(core.true_se2_at(t)[:2] - core.true_se2_at(t - 0.1)[:2])) > 1e-4
        if moving and len(views) > 1:
            views_moving += 1
            spread = np.linalg.norm(views[-1][:3, 3] - views[0][:3, 3])
            assert 0 < spread < 0.5 * 0.012 * (len(views) - 1) / len(views) * 2 + 1e-3
        if state.holding >= 0 and not moving:
            views_still += int(len(views) == 1)
        # the robot stands on the tilted plate: not level
        assert 0.0 < _slope_deg(core.T_world_base()) <= 0.5 + 1e-6
    assert views_moving > 5 and views_still > 0
    img = core.images()["cam0"]
    assert img.shape == (ring["cam0"].model.height, ring["cam0"].model.width)


def test_the_fisheye_ring_renders_detects_and_localizes():
    """config/ring_fisheye.yaml (equidistant lenses, ~131 deg): the renderer, the detector and the
    joint estimator through the pipeline handle it (exact rig, true map)."""
    from aruco_ring_localization.config import with_overrides as overrides
    from aruco_ring_localization.detection import Detector, DetectorParams
    from aruco_ring_localization.detections import CameraFrame, RingFrame
    from aruco_ring_localization.pipeline import LocalizationPipeline, feed_ring_frame
    from aruco_ring_localization.schemas import LocalizerConfig

    fish = CameraRing.load(os.path.join(REPO, "config", "ring_fisheye.yaml"))
    assert all(c.model.is_fisheye for c in fish.cameras)
    assert all(np.degrees(c.model.horizontal_fov()) > 120 for c in fish.cameras)
    scene = Scene.default()
    sim = RingSimulator(scene, fish, pixel_noise=0.0, seed=3)
    det = Detector(DetectorParams(dictionary=scene.dictionary))
    exact = fish.with_extrinsics_std(0.0, 0.0)
    config = overrides(LocalizerConfig(), {"input.use_tf": False, "input.camera_info_fallback": True})
    rng = np.random.default_rng(1)
    corner_err, found, visible = [], 0, 0
    for k, pose in enumerate([scene.test_positions[0], scene.test_positions[13]]):
        T = Scene.T_world_base(pose)
        frame = RingFrame(stamp=10.0 * k + 1.0)
        truth = sim.visible(T)
        for name, img in sim.render(T, rng=rng).items():
            obs = det.detect(img)
            frame.cameras[name] = CameraFrame(name, frame.stamp, obs)
            got = {o.marker_id: o.corners for o in obs}
            visible += len(truth[name])
            for marker_id, corners in truth[name]:
                if marker_id in got:
                    found += 1
                    corner_err.append(np.abs(got[marker_id] - corners).max())
        pipe = LocalizationPipeline(config, exact, scene.truth_map())
        feed_ring_frame(pipe, frame)
        est = pipe.last_track.localization
        e = geo.se2_from_transform(est.T_map_base) - np.asarray(pose)
        assert np.hypot(e[0], e[1]) < 0.005 and abs(geo.wrap_angle(e[2])) < np.radians(0.1), e
    assert visible > 40 and found >= 0.95 * visible, (found, visible)
    assert np.median(corner_err) < 0.3 and max(corner_err) < 1.0
