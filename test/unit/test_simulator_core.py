"""The simulator node's per-step logic without a master (SimulatorCore, SimulatorParams)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.simulator import SimulatorCore, SimulatorParams, waypoint_list
from aruco_ring_localization.simulation.scene import Scene

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="module")
def scene_ring():
    return Scene.default(), CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))


@pytest.mark.parametrize("kw, key", [({"mode": "video"}, "mode"), ({"waypoints": "all"}, "waypoints"),
                                     ({"drive": "fly"}, "drive"), ({"rate": 0.0}, "rate"),
                                     ({"start_pose": (1.0, 2.0)}, "start_pose")])
def test_bad_params_name_the_key(kw, key):
    with pytest.raises(ConfigError) as info:
        SimulatorParams(**kw).validate()
    assert info.value.key == key


def test_unknown_camera_is_an_error(scene_ring):
    with pytest.raises(ConfigError) as info:
        SimulatorCore(SimulatorParams(cameras=("cam9",)), *scene_ring)
    assert "cam9" in str(info.value)


def test_corners_mode_steps_through_the_test_positions(scene_ring):
    scene, ring = scene_ring
    core = SimulatorCore(SimulatorParams(waypoints="test_positions", drive="direct", hold_time=0.5, rate=10.0),
                         scene, ring)
    held = {}
    t = 0.0
    for _ in range(15 * 6 + 5):
        t += 0.1
        state = core.step(t, 0.1)
        if state.holding >= 0:
            held.setdefault(state.holding, state.pose.copy())
            dets = core.detections(t)
            assert sorted(dets) == ring.names
            assert sum(len(v) for v in dets.values()) >= 8
    assert sorted(held) == list(range(15)), sorted(held)
    for i, p in held.items():
        assert np.allclose(p, scene.test_positions[i]), (i, p)
    # The true rig differs from the calibration (seeded), as in the issue.
    d = core.true_ring["cam0"].T_base_cam[:3, 3] - ring["cam0"].T_base_cam[:3, 3]
    assert 0 < np.linalg.norm(d) < 0.01


def test_image_mode_subset_of_cameras(scene_ring):
    scene, ring = scene_ring
    core = SimulatorCore(SimulatorParams(mode="images", cameras=("cam2", "cam6"), waypoints="none"), scene, ring)
    core.step(0.1, 0.1)
    imgs = core.images()
    assert sorted(imgs) == ["cam2", "cam6"]
    assert imgs["cam2"].shape == (ring["cam2"].model.height, ring["cam2"].model.width)
    scan = core.scan()
    assert scan.shape == (360,) and np.all(np.isfinite(scan))


def test_waypoint_sets(scene_ring):
    scene, _ = scene_ring
    assert len(waypoint_list(scene, "paper")) == 23
    assert waypoint_list(scene, "none") == []


def test_teleport_is_a_kidnap_the_odometry_does_not_see(scene_ring):
    scene, ring = scene_ring
    core = SimulatorCore(SimulatorParams(waypoints="none"), scene, ring)
    for k in range(5):
        core.step(0.1 * k, 0.1)
    odom_before = core.state.odom_pose.copy()
    core.request_teleport(4.3, 3.8, np.radians(90.0))
    core.request_teleport(np.nan, 0.0, 0.0)            # ignored, the valid request stands
    state = core.step(0.5, 0.1)
    assert np.allclose(state.pose, [4.3, 3.8, np.radians(90.0)], atol=1e-9), state.pose
    assert np.allclose(state.odom_pose, odom_before, atol=1e-9), "odometry saw the kidnap"
    assert np.allclose(core.step(0.6, 0.1).pose, state.pose, atol=1e-9), "teleport applied twice or drifted"


def test_teleport_drive_is_direct_and_waypoints_are_listed(scene_ring):
    scene, ring = scene_ring
    core = SimulatorCore(SimulatorParams(waypoints="paper", drive="teleport", hold_time=0.2), scene, ring)
    assert core.waypoints() == [tuple(p) for p in scene.test_positions + scene.test_orientations]
    state = core.step(0.0, 0.1)
    assert np.allclose(state.pose, scene.test_positions[0]) and state.holding == 0, (state.pose, state.holding)
    assert SimulatorCore(SimulatorParams(waypoints="none"), scene, ring).waypoints() == []


def test_config_simulator_yaml_documents_real_parameters():
    """Every key of config/simulator.yaml is a simulator parameter, parses, and keeps the code's default."""
    import dataclasses

    from aruco_ring_localization.camera import load_yaml_file
    from aruco_ring_localization.ros.params import params_from_dict

    path = os.path.join(REPO, "config", "simulator.yaml")
    data = load_yaml_file(path)
    fields = {f.name for f in dataclasses.fields(SimulatorParams)}
    assert set(data) <= fields, f"unknown keys {sorted(set(data) - fields)}"
    assert params_from_dict(SimulatorParams, data, source=path).validate() == SimulatorParams()
