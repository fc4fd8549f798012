"""The demo's orchestration parts that need no master: the simulator's configuration per phase and
which frames belong to which stop (found from the ground truth alone)."""
from __future__ import annotations

import argparse
import os

import numpy as np
import pytest

from aruco_ring_localization.config import load_config
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros import demo
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.simulation.simulator import SimulatorCore

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def _args(**kw) -> argparse.Namespace:
    base = dict(mode="corners", rate=5.0, seed=0, hold_frames=10)
    base.update(kw)
    return argparse.Namespace(**base)


def test_simulator_configs_of_the_two_phases(tmp_path):
    scene = Scene.default()
    mapping, localization = demo.simulator_configs(_args(mode="images"), scene)
    for cfg in (mapping, localization):
        assert cfg.mode == "images" and cfg.rate == 5.0 and cfg.clock.publish and cfg.lockstep.enabled
        assert cfg.ring == SimulatorConfig().ring, "the true rig's error is the simulator's default"
    assert mapping.robot.waypoints == "none" and not mapping.robot.plan and not mapping.lockstep.topics
    route = localization.robot.plan
    stops = demo.plan_stops(scene.test_positions, scene.test_orientations)
    assert len(route) == 1 + len(stops) == 24
    assert np.allclose(route[0], [5.5, 4.5, 0.0]), "the route starts at the mapping placement"
    assert np.allclose([r[2] for r in route[1:]], [np.degrees(s.pose[2]) for s in stops])
    assert localization.robot.hold_time == pytest.approx(2.0)        # 10 frames at 5 Hz
    assert localization.lockstep.topics == ("localizer/pose",)
    # What the demo writes is what the simulator node reads back.
    path = demo.write_simulator_config(tmp_path / "sim.yaml", localization)
    from aruco_ring_localization.camera import load_yaml_file
    said = []
    assert load_config(SimulatorConfig, load_yaml_file(str(path)), warn=said.append) == localization and not said


def test_the_mapping_turn_is_one_full_turn_on_the_spot_at_the_given_rate():
    """--mapping-turn: the mapping phase turns once on the spot at the mapping pose (9 waypoints 45 deg
    apart, the last the start's heading, each held one frame) at the given yaw rate; 0 (the default)
    stands still there."""
    scene = Scene.default()
    still, _ = demo.simulator_configs(_args(mapping_turn=0.0), scene)
    assert still.robot.waypoints == "none" and not still.robot.plan
    assert demo._parse([]).mapping_turn == 0.0 and demo._parse(["--mapping-turn", "10"]).mapping_turn == 10.0
    turn, _ = demo.simulator_configs(_args(mapping_turn=10.0), scene)
    plan = np.array(turn.robot.plan)
    x0, y0, yaw0 = scene.mapping_pose
    assert plan.shape == (9, 3) and np.allclose(plan[:, :2], [x0, y0])
    assert np.allclose(np.diff(plan[:, 2]), 45.0) and plan[-1, 2] - plan[0, 2] == pytest.approx(360.0)
    assert turn.robot.limits.max_yaw_rate == pytest.approx(np.radians(10.0))
    assert turn.robot.hold_time == pytest.approx(0.2)                  # one frame at 5 Hz


def test_the_demo_runs_the_harsh_lab_by_default():
    from aruco_ring_localization.simulation.params import lab_config

    args = demo._parse([])
    assert args.lab == "harsh"
    mapping, localization = demo.simulator_configs(_args(lab="harsh"), Scene.default())
    harsh = lab_config("harsh")
    for cfg in (mapping, localization):
        assert (cfg.plate, cfg.ring, cfg.render, cfg.scene, cfg.cameras.trigger) == \
            (harsh.plate, harsh.ring, harsh.render, harsh.scene, "free")
    # 100 ms of phases at the demo's 5 Hz
    assert localization.cameras.phase_spread == pytest.approx(0.5)
    assert demo.simulator_configs(_args(lab="kind"), Scene.default())[0].plate == SimulatorConfig().plate


def _drive(config: SimulatorConfig, scene: Scene, frames_after: int = 15):
    """Ground truth of the simulator core driving the config's route, one pose per frame."""
    core = SimulatorCore(config, scene, CameraRing.load(os.path.join(REPO, "config", "ring.yaml")))
    dt = 1.0 / config.rate
    stamps, truth, held = [], [], []
    t = config.clock.start_time
    extra = 0
    while extra < frames_after:
        state = core.step(t, dt)
        stamps.append(round(t, 6))
        truth.append(state.pose.copy())
        held.append(state.holding)
        extra += core.finished
        t += dt
    return np.array(stamps), np.array(truth), np.array(held)


def test_stop_frames_are_the_held_frames_of_each_stop():
    scene = Scene.default()
    _, cfg = demo.simulator_configs(_args(), scene)
    stamps, truth, held = _drive(cfg, scene)
    route = [(x, y, np.radians(a)) for x, y, a in cfg.robot.plan]
    frames = demo.stop_frames(stamps, truth, route, cfg.robot.hold_time)
    assert len(frames) == len(route)
    for k, fr in enumerate(frames):
        assert 9 <= len(fr) <= 11, f"stop {k}: {len(fr)} frames"
        idx = np.searchsorted(stamps, fr)
        # Every frame of a stop is one where the simulator held that waypoint, at rest (after the
        # route the robot stays at the last stop: those frames count too)...
        assert np.all(held[idx] == k) or (k == len(route) - 1 and np.all(held[idx] <= k)), (k, held[idx])
        assert np.ptp(truth[idx], axis=0).max() < 1e-9
        # ... and the last ones (those a stop's estimate uses) are exactly the held frames' last.
        last_held = stamps[np.flatnonzero(held == k)[-1]]
        assert fr[-1] == last_held or k == len(route) - 1
        # The driver holds once within 5 mm of the goal, at under 1 cm/s: it coasts < 1 mm more.
        goal = np.array(route[k])
        assert np.hypot(*(truth[idx[-1], :2] - goal[:2])) < 0.006


def test_a_stop_without_a_rest_has_no_frames():
    scene = Scene.default()
    _, cfg = demo.simulator_configs(_args(), scene)
    stamps, truth, _ = _drive(cfg, scene)
    route = [(x, y, np.radians(a)) for x, y, a in cfg.robot.plan]
    bogus = route[:3] + [(1.0, 1.0, 0.0)] + route[3:]       # never visited: found no rest there
    frames = demo.stop_frames(stamps, truth, bogus, cfg.robot.hold_time)
    assert frames[3] == [] and all(len(f) >= 10 for k, f in enumerate(frames) if k != 3)


def test_the_demo_survey_is_seeded_noise_around_the_true_centres(tmp_path):
    """results/demo/anchors.yaml: 3 markers far apart, at their true centres + 1 mm seeded noise."""
    from aruco_ring_localization.anchors import frame_kind, load_anchors

    scene = Scene.default()
    truth = scene.truth_map()
    a = load_anchors(str(demo.write_survey(tmp_path / "a.yaml", scene, 3, 0.001, 13)))
    b = load_anchors(str(demo.write_survey(tmp_path / "b.yaml", scene, 3, 0.001, 13)))
    c = load_anchors(str(demo.write_survey(tmp_path / "c.yaml", scene, 3, 0.001, 14)))
    assert len(a.anchors) == 3 and frame_kind(a) == "points"
    d = np.array([truth.T_map_marker(x.marker_id)[:3, 3] - x.position for x in a.anchors])
    assert 0 < np.max(np.abs(d)) < 0.005, f"survey errors {d} m (1 mm noise)"
    assert all(np.array_equal(x.position, y.position) for x, y in zip(a.anchors, b.anchors)), "not seeded"
    assert not all(np.array_equal(x.position, y.position) for x, y in zip(a.anchors, c.anchors))
    P = np.array([x.position for x in a.anchors])
    assert min(np.linalg.norm(P[i] - P[j]) for i in range(3) for j in range(i)) > 3.0, f"not spread: {P}"
