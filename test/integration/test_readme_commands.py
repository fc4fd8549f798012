"""The README's and docs/install.md's commands as a new user types them (issue 15, items 1 and 4).

* ``rosrun aruco_ring_localization aruco_ring --help`` (docs/install.md) finds one executable and
  ``rosrun tf tf_echo`` exists (a ROS user's habit; ``make setup`` installs tf's tools);
* the README's ``localization.launch sim:=true rviz:=true`` without a saved map stops roslaunch
  with a non-zero exit naming the map file (it used to exit 0 after the localizer's FATAL).

The whole mapping -> save -> localize sequence is not run here (a rendered mapping run takes minutes
on a loaded machine); test/unit/test_newcomer_path.py checks that its commands agree with the launch
files.
"""
from __future__ import annotations

import os
import shlex
import socket
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENV_SH = REPO / ".ws" / "env.sh"

pytestmark = pytest.mark.skipif(not ENV_SH.is_file(), reason="no .ws/env.sh: run make setup")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run(cmd: str, env=None, timeout=60.0) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", f'source "{ENV_SH}" && {cmd}'], env=env, cwd=str(REPO),
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=timeout)


def _readme_line(start: str) -> str:
    text = (REPO / "README.md").read_text()
    block = text.split("## Using it", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    (line,) = [ln.split("#", 1)[0].strip() for ln in block.splitlines() if ln.startswith(start)]
    return line


def test_rosrun_finds_our_tool_once_and_tfs_tools():
    res = _run("rosrun aruco_ring_localization aruco_ring --help")
    assert res.returncode == 0 and "check-config" in res.stdout, res.stdout + res.stderr
    res = _run("rosrun tf tf_echo 2>&1 | head -1")
    assert "Usage: tf_echo" in res.stdout, res.stdout + res.stderr


def test_localization_without_a_saved_map_fails_naming_the_file(tmp_path):
    line = _readme_line("roslaunch aruco_ring_localization localization.launch")
    assert "sim:=true" in shlex.split(line), line
    env = dict(os.environ)
    env.update(ROS_HOME=str(tmp_path), ROS_MASTER_URI=f"http://localhost:{_free_port()}", ROS_HOSTNAME="localhost")
    env.pop("ROS_IP", None)
    try:
        res = _run(line, env=env, timeout=90.0)
    except subprocess.TimeoutExpired as exc:   # roslaunch started the nodes: the check is gone
        pytest.fail(f"roslaunch did not stop on the missing map: {str(exc.stdout)[-2000:]}")
    out = res.stdout + res.stderr
    assert res.returncode != 0, out[-2000:]
    assert str(tmp_path / "aruco_map.yaml") in out and "does not exist" in out, out[-2000:]
