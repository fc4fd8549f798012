"""The core imports without ROS: every module of the package outside ``ros/`` is imported in a
fresh interpreter in which importing rospy, tf2_ros, roslib or any ``*_msgs`` package fails (and
is recorded, so a guarded ``try: import rospy`` is caught as well)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import List

from helpers import REPO

SRC = REPO / "src"
PACKAGE = SRC / "aruco_ring_localization"

BLOCKER = r"""
import importlib, importlib.abc, json, sys

BLOCKED_ROOTS = {"rospy", "roslib", "rosgraph", "rospkg", "roslaunch", "rostest", "rosbag", "genpy", "genmsg",
                 "tf", "tf2_ros", "tf2_py", "tf2_geometry_msgs", "tf_conversions", "message_filters",
                 "actionlib", "cv_bridge", "image_geometry", "dynamic_reconfigure", "catkin", "catkin_pkg"}
attempts = []

class BlockRos(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        root = fullname.split(".")[0]
        if root in BLOCKED_ROOTS or root.endswith("_msgs") or root.endswith("_srvs"):
            attempts.append(fullname)
            raise ImportError(f"ROS module {fullname} is blocked in this test")
        return None

sys.meta_path.insert(0, BlockRos())
for name in list(sys.modules):
    if name.split(".")[0] in BLOCKED_ROOTS:
        del sys.modules[name]

failed = {}
for mod in json.loads(sys.argv[1]):
    try:
        importlib.import_module(mod)
    except Exception as exc:
        failed[mod] = f"{type(exc).__name__}: {exc}"
print(json.dumps({"failed": failed, "attempts": sorted(set(attempts))}))
"""


def core_modules() -> List[str]:
    """Every module under src/aruco_ring_localization except the ros/ package."""
    mods = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(SRC).with_suffix("")
        parts = list(rel.parts)
        if parts[1:2] == ["ros"]:
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods.append(".".join(parts))
    return mods


def _run(modules: List[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(SRC))
    # -I would drop PYTHONPATH; -s keeps user site-packages (where ROS could hide) out.
    proc = subprocess.run([sys.executable, "-s", "-c", BLOCKER, json.dumps(modules)], capture_output=True,
                          text=True, env=env, cwd=str(REPO), timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_core_module_list_is_complete():
    mods = core_modules()
    for expected in ("aruco_ring_localization", "aruco_ring_localization.geometry", "aruco_ring_localization.camera",
                     "aruco_ring_localization.rig", "aruco_ring_localization.markers",
                     "aruco_ring_localization.marker_map", "aruco_ring_localization.frames",
                     "aruco_ring_localization.fileio", "aruco_ring_localization.errors",
                     "aruco_ring_localization.cli", "aruco_ring_localization.cli.check_config"):
        assert expected in mods, f"{expected} missing from {mods}"
    assert not [m for m in mods if ".ros" in m]


def test_every_core_module_imports_without_ros():
    result = _run(core_modules())
    assert result["failed"] == {}, f"core modules failed to import without ROS: {result['failed']}"
    assert result["attempts"] == [], f"core modules tried to import ROS packages: {result['attempts']}"


def test_the_blocker_catches_a_ros_import():
    # The harness must be able to fail: the ROS adapters do import rospy / messages.
    ros_mods = [f"aruco_ring_localization.ros.{p.stem}" for p in sorted((PACKAGE / "ros").glob("*.py"))
                if p.stem != "__init__"]
    assert ros_mods, "no modules in ros/"
    result = _run(ros_mods)
    assert result["attempts"], f"no ROS import was seen while importing {ros_mods}"
    # conversions.py is the message layer: it cannot import without the messages.
    assert "aruco_ring_localization.ros.conversions" in result["failed"], result
