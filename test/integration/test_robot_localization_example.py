"""launch/robot_localization_example.launch and config/robot_localization_ekf.yaml, checked without
robot_localization (Debian 12 does not package it): roslaunch resolves the file (arguments,
includes, parameters) with ``--nodes`` / ``--dump-params``, and what the EKFs are told to fuse is
what the localizer publishes (topic, frames, the components ~pose carries)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing

REPO = Path(__file__).resolve().parents[2]
ENV_SH = REPO / ".ws" / "env.sh"
LAUNCH = REPO / "launch" / "robot_localization_example.launch"
MAP = REPO / "test" / "data" / "lab_truth_map.yaml"

pytestmark = pytest.mark.skipif(not ENV_SH.is_file(), reason="no .ws/env.sh: run make setup")


def _roslaunch(*args: str) -> str:
    cmd = " ".join(["roslaunch", *args, str(LAUNCH), f"map_file:={MAP}"])
    proc = subprocess.run(["bash", "-c", f'source "{ENV_SH}" && {cmd}'], cwd=str(REPO), stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{cmd} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    return proc.stdout


def test_the_launch_file_resolves_without_robot_localization():
    nodes = _roslaunch("--nodes").split()
    assert nodes == ["/ring_tf", "/localizer", "/ekf_map"], nodes
    nodes = _roslaunch("--nodes", "odom_ekf:=true").split()
    assert "/ekf_odom" in nodes


def test_the_ekf_fuses_what_the_localizer_publishes():
    flat = yaml.safe_load(_roslaunch("--dump-params", "odom_ekf:=true", "odom_topic:=wheel/odom"))

    def node(name: str) -> dict:
        return {k[len(name) + 1:]: v for k, v in flat.items() if k.startswith(name + "/")}

    ekf, local, loc = node("/ekf_map"), node("/ekf_odom"), node("/localizer")
    # the localizer leaves map -> odom to the EKF
    assert loc["output/publish_tf"] is False
    assert ekf["publish_tf"] is True and ekf["world_frame"] == ekf["map_frame"]
    # its pose topic (the node's ~pose), frames of the map and the ring
    assert "/" + ekf["pose0"] == "/localizer/pose"
    assert ekf["map_frame"] == MarkerMap.load(str(MAP)).frame_id
    ring = CameraRing.load(str(REPO / "config" / "ring.yaml"))
    assert ekf["base_link_frame"] == local["base_link_frame"] == ring.base_frame
    assert ekf["odom_frame"] == local["odom_frame"] == local["world_frame"] == loc["output/odom_frame"]
    # ~pose is good for x, y, yaw only; the wheel odometry for its velocities only
    assert [i for i, on in enumerate(ekf["pose0_config"]) if on] == [0, 1, 5]
    for cfg in (ekf["odom0_config"], local["odom0_config"]):
        assert [i for i, on in enumerate(cfg) if on] == [6, 7, 11]
    assert ekf["odom0"] == local["odom0"] == "wheel/odom"
    assert ekf["two_d_mode"] is True and len(ekf["pose0_config"]) == 15
