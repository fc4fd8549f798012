"""Ring simulator, corners mode: projection, visibility rules, occlusion, noise, true vs calibrated rig."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Plate, Room, Scene, SceneMarker, marker_pose

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="module")
def ring():
    return CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))


@pytest.fixture(scope="module")
def lab():
    return Scene.default()


def _scene(markers):
    return Scene(name="t", world_frame="world", room=Room((-20.0, -20.0), (40.0, 40.0)),
                 plate=Plate((0.0, 0.0), (2.0, 2.0)), markers=markers)


def _facing_cam0(mid, x, y=0.0, z=0.75, size=0.2, turn_deg=0.0):
    """A marker in front of cam0 (robot at the origin, yaw 0) facing back at it."""
    return SceneMarker(mid, marker_pose([x, y, z], np.pi + np.radians(turn_deg)), size)


def test_perturb_ring_is_seeded_and_small(ring):
    a, b, c = perturb_ring(ring, seed=3), perturb_ring(ring, seed=3), perturb_ring(ring, seed=4)
    for cam in ring.cameras:
        assert np.array_equal(a[cam.name].T_base_cam, b[cam.name].T_base_cam)
        dt, dr = geo.pose_distance(cam.T_base_cam, a[cam.name].T_base_cam)
        assert 0 < dt < 0.012 and 0 < np.degrees(dr) < 1.2, (cam.name, dt, np.degrees(dr))
        assert not np.array_equal(a[cam.name].T_base_cam, c[cam.name].T_base_cam)
    assert a.names == ring.names


def test_projection_matches_the_camera_model(ring):
    scene = _scene([_facing_cam0(5, 3.0)])
    sim = RingSimulator(scene, ring, pixel_noise=0.0)
    vis = sim.visible(np.eye(4))
    assert [i for i, _ in vis["cam0"]] == [5]
    assert all(not v for name, v in vis.items() if name != "cam0")
    cam = ring["cam0"]
    T_cam_marker = geo.inverse(cam.T_base_cam) @ scene.markers[0].T_world_marker
    expected = cam.model.project(geo.transform_points(T_cam_marker, marker_corners(0.2)))
    assert np.allclose(vis["cam0"][0][1], expected, atol=1e-9)
    c = vis["cam0"][0][1]
    # aruco_detect order as seen in the image: 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left.
    assert c[0, 0] < c[1, 0] and c[3, 0] < c[2, 0] and c[0, 1] < c[3, 1] and c[1, 1] < c[2, 1], c


def test_marker_seen_from_behind_or_too_oblique_is_not_visible(ring):
    sim = RingSimulator(_scene([SceneMarker(1, marker_pose([3.0, 0.0, 0.75], 0.0), 0.2)]), ring)
    assert not sim.visible(np.eye(4))["cam0"]                     # faces away
    sim = RingSimulator(_scene([_facing_cam0(1, 3.0, turn_deg=80.0)]), ring)
    assert not sim.visible(np.eye(4))["cam0"]                     # 80 deg > 75 deg
    sim = RingSimulator(_scene([_facing_cam0(1, 3.0, turn_deg=60.0)]), ring)
    assert sim.visible(np.eye(4))["cam0"]


def test_range_and_pixel_size_limits(ring):
    far = RingSimulator(_scene([_facing_cam0(1, 9.0)]), ring, max_range=8.0)
    assert not far.visible(np.eye(4))["cam0"]
    ok = RingSimulator(_scene([_facing_cam0(1, 7.5)]), ring, max_range=8.0)
    assert ok.visible(np.eye(4))["cam0"]
    tiny = RingSimulator(_scene([_facing_cam0(1, 7.5, size=0.1)]), ring, max_range=8.0)
    v = tiny.camera_view(np.eye(4), "cam0")
    assert not v, [x.pixel_size for x in v]  # 0.1 m at 7.5 m is about 11 px < 15 px


def test_partly_outside_image_is_not_visible(ring):
    # Far to the side of cam0 at the image edge: half the marker outside the field of view.
    cam = ring["cam0"]
    half_fov = cam.model.horizontal_fov() / 2
    y = 3.0 * np.tan(half_fov)
    sim = RingSimulator(_scene([_facing_cam0(1, 3.0, y=-y)]), ring)
    assert not sim.visible_camera(np.eye(4), "cam0")


def test_nearer_marker_occludes_farther(ring):
    near, far = _facing_cam0(1, 2.0), _facing_cam0(2, 4.0, y=0.05)
    sim = RingSimulator(_scene([far, near]), ring)
    assert [i for i, _ in sim.visible(np.eye(4))["cam0"]] == [1]
    # Moved aside, both are seen (nearest first).
    sim = RingSimulator(_scene([_facing_cam0(2, 4.0, y=-1.0), near]), ring)
    assert [i for i, _ in sim.visible(np.eye(4))["cam0"]] == [1, 2]


def test_observe_noise_is_seeded_and_has_the_right_scale(ring, lab):
    sim_a = RingSimulator(lab, ring, pixel_noise=0.5, seed=7)
    sim_b = RingSimulator(lab, ring, pixel_noise=0.5, seed=7)
    pose = lab.mapping_pose
    fa, fb = sim_a.observe(pose, 1.5), sim_b.observe(pose, 1.5)
    assert fa.stamp == 1.5 and sorted(fa.cameras) == sorted(ring.names) and not fa.missing
    truth = sim_a.visible(pose)
    errs = []
    for name, cf in fa.cameras.items():
        assert cf.camera == name and cf.stamp == 1.5
        assert [o.marker_id for o in cf.observations] == [i for i, _ in truth[name]]
        for o, ob, (_, c) in zip(cf.observations, fb.cameras[name].observations, truth[name]):
            assert np.array_equal(o.corners, ob.corners)
            errs.append(o.corners - c)
    errs = np.concatenate(errs).ravel()
    assert errs.size >= 80
    assert 0.35 < errs.std() < 0.65, f"noise std {errs.std():.3f} px, expected ~0.5"
    assert not np.array_equal(sim_a.observe(pose, 2.0).cameras["cam0"].observations[0].corners,
                              fa.cameras["cam0"].observations[0].corners)


def test_lab_coverage_from_every_test_pose(ring, lab):
    """From every test pose several markers are seen; from the mapping pose every marker is seen
    and some camera sees two markers at once (the mapping chain needs co-visible pairs)."""
    sim = RingSimulator(lab, perturb_ring(ring), pixel_noise=0.0)
    for pose in lab.test_positions + lab.test_orientations:
        vis = sim.visible(pose)
        n = sum(len(v) for v in vis.values())
        cams = sum(1 for v in vis.values() if v)
        assert n >= 8 and cams >= 5, (pose, n, cams)
    vis = sim.visible(lab.mapping_pose)
    seen = {i for v in vis.values() for i, _ in v}
    assert seen == set(lab.marker_ids), sorted(set(lab.marker_ids) - seen)
    pairs = sum(1 for v in vis.values() if len(v) >= 2)
    assert pairs >= 4, pairs
    multi = [i for i in lab.marker_ids if sum(any(j == i for j, _ in v) for v in vis.values()) >= 2]
    assert len(multi) >= 3, multi


def test_accepts_se2_or_matrix(ring, lab):
    sim = RingSimulator(lab, ring, pixel_noise=0.0)
    a = sim.visible((5.0, 4.0, 0.3))
    b = sim.visible(geo.transform_from_se2(5.0, 4.0, 0.3))
    assert all(np.allclose(x[1], y[1]) for k in a for x, y in zip(a[k], b[k]))
