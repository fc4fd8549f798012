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
                     "aruco_ring_localization.ring", "aruco_ring_localization.markers",
                     "aruco_ring_localization.marker_map", "aruco_ring_localization.detections",
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


# --- static check: every import statement, at any indentation -------------------------------------
# Importing a module only shows the imports that run at import time; an ``import rosbag`` inside a
# function runs later. So every ``import``/``from ... import`` node of every core file is read.
ROS_ROOTS = {"rospy", "rosbag", "tf2_ros", "genpy", "roslib", "rosgraph", "roslaunch", "rostest", "tf",
             "tf2_py", "message_filters", "cv_bridge", "rospkg", "actionlib", "dynamic_reconfigure"}
# The command-line entry point may hand a bag command to our ros/ package; nothing else in the core may.
MAY_USE_OUR_ROS_PACKAGE = ("cli",)


def _is_ros_module(name: str) -> bool:
    root = name.split(".")[0]
    return root in ROS_ROOTS or root.endswith("_msgs") or root.endswith("_srvs")


def ros_imports_in(path) -> List[str]:
    """``line: module`` of every ROS import in one file, at any indentation (also our own ``ros``
    package, outside the entry points that may use it)."""
    import ast

    rel = path.relative_to(PACKAGE).parts
    allowed_own_ros = rel[0] in MAY_USE_OUR_ROS_PACKAGE
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found = []
    for node in ast.walk(tree):
        names: List[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against the file's package
                pkg = list(("aruco_ring_localization",) + rel[:-1])
                pkg = pkg[: len(pkg) - (node.level - 1)]
                full = ".".join(pkg + ([base] if base else []))
                names = [full] if base else [f"{full}.{a.name}" for a in node.names]
            else:
                names = [base]
        for n in names:
            own_ros = n == "aruco_ring_localization.ros" or n.startswith("aruco_ring_localization.ros.")
            if _is_ros_module(n) or (own_ros and not allowed_own_ros):
                found.append(f"{node.lineno}: {n}")
    return found


def test_no_ros_import_statement_anywhere_in_the_core():
    bad = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.relative_to(PACKAGE).parts[0] == "ros":
            continue
        hits = ros_imports_in(path)
        if hits:
            bad[str(path.relative_to(REPO))] = hits
    assert not bad, f"ROS imports in the core (move them under ros/): {bad}"


def test_the_static_check_sees_nested_and_relative_imports(tmp_path):
    # It must be able to fail: an import inside a function, a relative import of ..ros, a *_msgs.
    probe = PACKAGE / "simulation" / "_probe_for_test.py"
    probe.write_text("def f():\n    import rosbag\n    from ..ros import conversions\n"
                     "    from geometry_msgs.msg import Pose\n", encoding="utf-8")
    try:
        hits = ros_imports_in(probe)
    finally:
        probe.unlink()
    assert hits == ["2: rosbag", "3: aruco_ring_localization.ros", "4: geometry_msgs.msg"], hits
