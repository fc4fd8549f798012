"""The simulator node's per-step logic and parameter schema without a master (SimulatorCore, SimulatorConfig)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization.config import load_config, with_overrides
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.scene import Scene, resolve_scene_file
from aruco_ring_localization.simulation.simulator import SimulatorCore, waypoint_list

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="module")
def scene_ring():
    return Scene.default(), CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))


def config(**dotted) -> SimulatorConfig:
    """The default schema with dotted-key overrides, e.g. config(**{"robot.drive": "direct"})."""
    return with_overrides(SimulatorConfig(), dotted)


@pytest.mark.parametrize("values, key", [
    ({"mode": "video"}, "mode"), ({"robot": {"waypoints": "all"}}, "robot.waypoints"),
    ({"robot": {"drive": "fly"}}, "robot.drive"), ({"rate": 0.0}, "rate"),
    ({"robot": {"start_pose": [1.0, 2.0]}}, "robot.start_pose"),
    ({"robot": {"plan": [[1.0, 2.0, 0.0], [1.0, "x", 0.0]]}}, "robot.plan[1]"),
    ({"robot": {"limits": {"max_speed": -1.0}}}, "robot.limits.max_speed"),
    ({"clock": {"speed": 0}}, "clock.speed"), ({"lockstep": {"timeout": 0.0}}, "lockstep.timeout"),
    ({"render": {"supersample": 0}}, "render.supersample"), ({"cameras": {"max_range": -1.0}}, "cameras.max_range")])
def test_bad_params_name_the_dotted_key(values, key):
    with pytest.raises(ConfigError) as info:
        load_config(SimulatorConfig, values, source="simulator.yaml")
    assert info.value.key == key, str(info.value)
    assert "simulator.yaml" in str(info.value)


def test_unknown_camera_is_an_error(scene_ring):
    with pytest.raises(ConfigError) as info:
        SimulatorCore(config(**{"cameras.names": ("cam9",)}), *scene_ring)
    assert "cam9" in str(info.value) and info.value.key == "cameras.names"


def test_corners_mode_steps_through_the_test_positions(scene_ring):
    scene, ring = scene_ring
    core = SimulatorCore(config(**{"robot.waypoints": "test_positions", "robot.drive": "direct",
                                   "robot.hold_time": 0.5, "rate": 10.0}), scene, ring)
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
    core = SimulatorCore(config(mode="images", **{"cameras.names": "cam2 cam6", "robot.waypoints": "none"}),
                         scene, ring)
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
    core = SimulatorCore(config(**{"robot.waypoints": "none"}), scene, ring)
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
    core = SimulatorCore(config(**{"robot.waypoints": "paper", "robot.drive": "teleport", "robot.hold_time": 0.2}),
                         scene, ring)
    assert core.waypoints() == [tuple(p) for p in scene.test_positions + scene.test_orientations]
    state = core.step(0.0, 0.1)
    assert np.allclose(state.pose, scene.test_positions[0]) and state.holding == 0, (state.pose, state.holding)
    assert SimulatorCore(config(**{"robot.waypoints": "none"}), scene, ring).waypoints() == []




def test_an_explicit_plan_replaces_the_named_waypoints(scene_ring):
    scene, ring = scene_ring
    plan = [[5.5, 4.5, 0.0], [4.3, 3.8, 90.0], [4.3, 3.8, -45.0]]
    core = SimulatorCore(config(**{"robot.plan": plan, "robot.waypoints": "none", "robot.drive": "direct",
                                   "robot.hold_time": 0.25}), scene, ring)
    assert np.allclose(core.waypoints(), [(x, y, np.radians(a)) for x, y, a in plan])
    held, t = [], 0.0
    while not core.finished and t < 10.0:
        t += 0.1
        state = core.step(t, 0.1)
        if state.holding >= 0 and (not held or held[-1][0] != state.holding):
            held.append((state.holding, state.pose.copy()))
    assert [k for k, _ in held] == [0, 1, 2], held
    assert np.allclose(held[1][1], (4.3, 3.8, np.pi / 2)) and np.allclose(held[2][1], (4.3, 3.8, -np.pi / 4))
    assert core.step(t + 0.1, 0.1).holding == -1, "finished: no waypoint is held any more"


def test_config_simulator_yaml_mirrors_the_schema():
    """config/simulator.yaml has every key of SimulatorConfig, nothing else, with the same defaults."""
    from aruco_ring_localization.camera import load_yaml_file
    from aruco_ring_localization.config import flatten

    path = os.path.join(REPO, "config", "simulator.yaml")
    data = load_yaml_file(path)

    def leaves(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from leaves(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    in_yaml = dict(leaves(data))
    in_schema = {k: d for k, d, _, _ in flatten(SimulatorConfig)}
    assert sorted(in_yaml) == sorted(in_schema)
    different = {k: (v, in_schema[k]) for k, v in in_yaml.items()
                 if (tuple(v) if isinstance(v, list) else v) != in_schema[k]}
    assert not different, f"YAML value vs schema default: {different}"
    warnings = []
    assert load_config(SimulatorConfig, data, source=path, warn=warnings.append) == SimulatorConfig()
    assert not warnings
    undocumented = [k for k, _, doc, _ in flatten(SimulatorConfig) if not doc]
    assert not undocumented, f"schema fields without a doc: {undocumented}"


def test_simulation_launch_args_only_override_when_given():
    """Every simulator <param> of simulation.launch is a schema key set only when its argument (by
    default "yaml") is given: none shadows a key of config/simulator.yaml."""
    import xml.etree.ElementTree as ET

    from aruco_ring_localization.config import flatten

    root = ET.parse(os.path.join(REPO, "launch", "simulation.launch")).getroot()
    args = {a.get("name"): a.get("default") for a in root.findall("arg")}
    node = next(n for n in root.iter("node") if n.get("type") == "simulator")
    keys = {k for k, _, _, _ in flatten(SimulatorConfig)}
    mapped = {}
    for p in node.iter("param"):
        value = p.get("value")
        assert value.startswith("$(arg ") and value.endswith(")"), ET.tostring(p)
        arg = value[len("$(arg "):-1]
        assert p.get("if") == f"$(eval arg('{arg}') != 'yaml')", f"param {p.get('name')} is set unconditionally"
        assert p.get("name").replace("/", ".") in keys, f"{p.get('name')} is not a simulator parameter"
        mapped[arg] = p.get("name")
    launch_only = {"config", "lab", "detectors", "corner_refinement", "sim_time"}
    assert set(args) == set(mapped) | launch_only, sorted(set(args) ^ (set(mapped) | launch_only))
    for arg in mapped:
        assert args[arg] in ("yaml", "$(arg sim_time)"), f"arg {arg} defaults to {args[arg]!r}, not the YAML's value"
    loads = [(r.get("file"), r.get("if")) for r in node.iter("rosparam")]
    assert loads == [("$(arg config)", None), ("$(find aruco_ring_localization)/config/lab_$(arg lab).yaml",
                                               "$(eval arg('lab') != 'kind')")]
    assert args["config"].endswith("/config/simulator.yaml") and args["lab"] == "kind"


@pytest.mark.parametrize("lab", ["harsh", "kind"])
def test_lab_files_hold_only_simulator_keys(lab):
    """config/lab_<lab>.yaml (loaded over config/simulator.yaml by simulation.launch lab:=...) holds
    known keys only, with valid values; kind changes nothing, harsh changes each harsh model."""
    from aruco_ring_localization.camera import load_yaml_file
    from aruco_ring_localization.simulation.params import lab_config, lab_file

    unknown = []
    load_config(SimulatorConfig, load_yaml_file(lab_file(lab)) or {}, source=lab_file(lab), unknown=unknown,
                warn=lambda msg: None)
    assert not unknown, unknown
    c = lab_config(lab)
    if lab == "kind":
        assert c == SimulatorConfig()
    else:
        assert c.cameras.trigger == "free" and 0 < c.plate.tilt_deg + c.plate.bump_deg <= 0.5
        assert c.ring.vibration_rot_std_deg == 0.05 and c.render.exposure_time > 0
        assert c.render.gain_std > 0 and c.render.illumination_gradient > 0
        assert Scene.load(resolve_scene_file(c.scene.file)).occluders


def test_header_stamp_reads_any_stamped_message():
    import struct

    from aruco_ring_localization.ros.simulator import header_stamp

    frame = b"map"
    raw = struct.pack("<III", 7, 1234, 500_000_000) + struct.pack("<I", len(frame)) + frame + b"\x00" * 56
    assert header_stamp(raw) == pytest.approx(1234.5, abs=1e-9)
    assert header_stamp(b"\x00" * 8) is None


def test_lockstep_topics_must_start_with_a_header():
    from aruco_ring_localization.ros.simulator import _starts_with_header

    pose_with_cov = "# This expresses an estimated pose\n\nHeader header\nPoseWithCovariance pose\n"
    assert _starts_with_header(pose_with_cov)
    assert _starts_with_header("std_msgs/Header header  # stamped\nfloat64 x")
    assert not _starts_with_header("# just a number\nfloat64 data\n")
    assert not _starts_with_header("")


def test_the_gmapping_stand_in_puts_base_link_at_its_true_pose(scene_ring):
    """map -> odom of the perfect gmapping, composed with the drifting odom -> base_link, is the truth."""
    scene, ring = scene_ring
    core = SimulatorCore(config(**{"robot.waypoints": "test_positions", "gmapping.publish": True}), scene, ring)
    for k in range(60):
        core.step(0.1 * k, 0.1)
    assert np.linalg.norm(core.state.pose[:2] - core.state.odom_pose[:2]) > 1e-4 or \
        abs(core.state.pose[2] - core.state.odom_pose[2]) > 1e-6, "the odometry did not drift: nothing is tested"
    T = core.T_world_odom() @ Scene.T_world_base(core.state.odom_pose)
    assert np.allclose(T, Scene.T_world_base(core.state.pose), atol=1e-12)
    cells, origin = core.occupancy_grid()
    assert (cells == 100).any() and origin[0] < scene.room.origin[0] and origin[1] < scene.room.origin[1]
