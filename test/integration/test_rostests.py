"""Runs every rostest file in test/integration/ (``*.test``) as one pytest test.

So that ONE pytest invocation covers the unit tests and the node-level rostests, and its
closing line counts both. Each file runs as ``rostest --text aruco_ring_localization <file>``
in the set-up workspace (``.ws/env.sh`` sourced when it exists), with ``ROS_HOME`` inside the
workspace and ``ROS_HOSTNAME=localhost``; rostest picks a free master port, so a running
roscore does not interfere. The subprocess has a timeout (``ARUCO_RING_ROSTEST_TIMEOUT``,
seconds, default 600) and a failure shows the tail of rostest's output.

``rostest --text`` exits 0 even when a test case fails (it says so: "overall test result is not
accurate when --text is enabled"), so success also requires rostest's own summary to read
``RESULT: SUCCESS`` with at least one test, no error and no failure.

A file whose text says ``hostile-only`` (the slower hostile-input rostests) runs only when
``ARUCO_RING_HOSTILE=1`` (``make hostile``); ``make test`` reports it skipped.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path
from typing import Dict, List

import pytest

PKG = "aruco_ring_localization"
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
ENV_SH = REPO / ".ws" / "env.sh"
TIMEOUT_S = float(os.environ.get("ARUCO_RING_ROSTEST_TIMEOUT", "600"))
TAIL_LINES = 120

ROSTEST_FILES: List[Path] = sorted(HERE.glob("*.test"))
RUN_HOSTILE_ONLY = os.environ.get("ARUCO_RING_HOSTILE", "") == "1"


def _params(files: List[Path]) -> list:
    skip = pytest.mark.skipif(not RUN_HOSTILE_ONLY, reason="hostile-only: make hostile (ARUCO_RING_HOSTILE=1)")
    return [pytest.param(p, id=p.stem, marks=[skip] if "hostile-only" in p.read_text() else [])
            for p in files]


def _rostest_env() -> Dict[str, str]:
    env = dict(os.environ)
    env.setdefault("ROS_HOME", str(REPO / ".ws" / "ros_home"))
    env["ROS_HOSTNAME"] = "localhost"
    env.pop("ROS_IP", None)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _command(test_file: Path) -> List[str]:
    rostest = f"rostest --text {PKG} {test_file.name}"
    if ENV_SH.is_file():
        # Source the workspace so rostest finds the package and the venv's Python.
        return ["bash", "-c", f'source "{ENV_SH}" && exec {rostest}']
    return ["bash", "-c", f"exec {rostest}"]


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_SUMMARY = re.compile(r"^ \* (RESULT|TESTS|ERRORS|FAILURES): (\S+)", re.MULTILINE)


def _summary(output: str) -> Dict[str, str]:
    """rostest's closing summary, e.g. {'RESULT': 'SUCCESS', 'TESTS': '2', 'ERRORS': '0', 'FAILURES': '0'}."""
    return dict(_SUMMARY.findall(_ANSI.sub("", output)))


def _tail(text: str, lines: int = TAIL_LINES) -> str:
    return "\n".join(text.splitlines()[-lines:])


def test_rostest_files_exist():
    assert ROSTEST_FILES, f"no *.test files in {HERE}"


@pytest.mark.parametrize("test_file", _params(ROSTEST_FILES))
def test_rostest(test_file: Path):
    env = _rostest_env()
    Path(env["ROS_HOME"]).mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(_command(test_file), cwd=str(REPO), env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            universal_newlines=True, start_new_session=True)
    try:
        output, _ = proc.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        # rostest starts a master and nodes: end the whole process group, not just bash.
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            output, _ = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            output, _ = proc.communicate()
        pytest.fail(f"rostest {test_file.name} timed out after {TIMEOUT_S:.0f} s; last output:\n{_tail(output)}")
    summary = _summary(output)
    ok = (proc.returncode == 0 and summary.get("RESULT") == "SUCCESS" and summary.get("TESTS", "0") != "0"
          and summary.get("ERRORS") == "0" and summary.get("FAILURES") == "0")
    assert ok, (f"rostest {test_file.name} failed (exit code {proc.returncode}, summary {summary or 'missing'}); "
                f"last output:\n{_tail(output)}")
