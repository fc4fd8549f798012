"""Renders each rviz configuration headless and fails if rviz reports an error status for a display.

For each ``rviz/*.rviz``: a roscore on a free port, ``rviz_scene_publisher.py`` publishing every
topic and frame the configurations show (the simulated lab, robot at the plate centre), then
``xvfb-run rviz_check.py CONFIG`` (rviz through its Python bindings: loads the config, runs
``RVIZ_SECONDS`` s, prints each display's status, screenshots the virtual screen with ImageMagick's
``import -window root``) into ``results/rviz/<config>.png``. A display whose status is Error fails
the test with rviz's status text. A control case (an Axes display on a frame nobody publishes)
must come out as Error, so the check itself is known to work.

Skipped, with the reason, only when rviz, its Python bindings, xvfb-run or ImageMagick are not
installed (``make setup`` installs them).
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Tuple

import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
ENV_SH = REPO / ".ws" / "env.sh"
OUT = REPO / "results" / "rviz"
CONFIGS = sorted((REPO / "rviz").glob("*.rviz"))
SECONDS = float(os.environ.get("RVIZ_SECONDS", "10"))
# Mesa's llvmpipe cannot link one of rviz's Map shaders; rviz logs it as [ERROR] and draws the map
# anyway (the screenshot shows it). Any other [ERROR] line fails the test.
BENIGN_ERRORS = (re.compile(r"glsl120/indexed_8bit_image"), re.compile(r"GLSL link result"),
                 re.compile(r"active samplers with a different type"))


def _missing() -> List[str]:
    missing = [tool for tool in ("rviz", "xvfb-run", "import", "roscore") if shutil.which(tool) is None]
    # cwd: not the repository root, whose rviz/ folder (the configs) would shadow the rviz package
    probe = subprocess.run([sys.executable, "-c", "from rviz import bindings"], capture_output=True, cwd=str(HERE))
    if probe.returncode != 0:
        missing.append("python3-rviz (rviz's Python bindings)")
    return missing


pytestmark = pytest.mark.skipif(bool(_missing()), reason=f"not installed: {', '.join(_missing())} (make setup installs them)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _env(port: int) -> Dict[str, str]:
    env = dict(os.environ)
    env["ROS_MASTER_URI"] = f"http://localhost:{port}"
    env["ROS_HOSTNAME"] = "localhost"
    env.pop("ROS_IP", None)
    env.setdefault("ROS_HOME", str(REPO / ".ws" / "ros_home"))
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _spawn(cmd: str, env: Dict[str, str]) -> subprocess.Popen:
    prefix = f'source "{ENV_SH}" && ' if ENV_SH.is_file() else ""
    return subprocess.Popen(["bash", "-c", prefix + "exec " + cmd], env=env, cwd=str(REPO), stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True,
                            start_new_session=True)


def _stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
    out, _ = proc.communicate()
    return out or ""


@pytest.fixture(scope="module")
def ros_scene():
    port = _free_port()
    env = _env(port)
    Path(env["ROS_HOME"]).mkdir(parents=True, exist_ok=True)
    core = _spawn(f"roscore -p {port}", env)
    pub = None
    try:
        deadline = time.time() + 30
        while time.time() < deadline:
            if subprocess.run(["bash", "-c", (f'source "{ENV_SH}" && ' if ENV_SH.is_file() else "") + "rostopic list"],
                              env=env, capture_output=True).returncode == 0:
                break
            time.sleep(0.5)
        else:
            pytest.fail(f"roscore on port {port} did not come up:\n{_stop(core)}")
        pub = _spawn(f"python {HERE / 'rviz_scene_publisher.py'}", env)
        time.sleep(3.0)
        assert pub.poll() is None, f"the scene publisher died:\n{_stop(pub)}"
        yield env
    finally:
        if pub is not None:
            _stop(pub)
        _stop(core)


def _run_rviz(config: Path, png: Path, env: Dict[str, str]) -> Tuple[List[Tuple[str, str, str, str]], str]:
    png.parent.mkdir(parents=True, exist_ok=True)
    cmd = (f'xvfb-run -a -s "-screen 0 1400x900x24" python {HERE / "rviz_check.py"} "{config}" "{png}" {SECONDS}')
    proc = _spawn(cmd, env)
    try:
        out, _ = proc.communicate(timeout=SECONDS + 90)
    except subprocess.TimeoutExpired:
        out = _stop(proc)
        pytest.fail(f"rviz on {config.name} did not finish:\n{out[-3000:]}")
    displays = []
    for line in out.splitlines():
        if line.startswith("DISPLAY "):
            parts = [p.strip() for p in line[len("DISPLAY "):].split("|")]
            displays.append(tuple(parts + [""] * (4 - len(parts)))[:4])
    return displays, out


def _unexpected_errors(output: str) -> List[str]:
    lines = re.sub(r"\x1b\[[0-9;]*m", "", output).splitlines()
    errors = []
    for k, line in enumerate(lines):
        if "[ERROR]" in line or "CONFIG_ERROR" in line:
            block = " ".join(lines[k:k + 4])
            if not any(p.search(block) for p in BENIGN_ERRORS):
                errors.append(line)
    return errors


#: What both configurations must show (issue 15): the map (gmapping's grid and our markers), the ring's
#: fields of view, the robot (tf and its marker) and the scan.
REQUIRED = {"rviz/Map": "/map", "rviz/LaserScan": "/scan", "rviz/MarkerArray": "/ring_tf/markers", "rviz/TF": None}


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_rviz_config_shows_the_map_the_ring_the_robot_and_the_scan(config: Path):
    import yaml

    displays = yaml.safe_load(config.read_text())["Visualization Manager"]["Displays"]
    shown = {(d.get("Class"), d.get("Topic") or d.get("Marker Topic")) for d in displays if d.get("Enabled", True)}
    for cls, topic in REQUIRED.items():
        assert any(c == cls and (topic is None or t == topic) for c, t in shown), \
            f"{config.name}: no enabled {cls} display{' on ' + topic if topic else ''}; displays: {sorted(shown)}"


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_rviz_config_renders_without_errors(config: Path, ros_scene):
    png = OUT / f"{config.stem}.png"
    displays, out = _run_rviz(config, png, ros_scene)
    assert displays, f"rviz printed no display for {config.name}; output:\n{out[-3000:]}"
    bad = [d for d in displays if d[2].lower().startswith("error")]
    assert not bad, f"{config.name}: displays in error: {bad}"
    errors = _unexpected_errors(out)
    assert not errors, f"{config.name}: rviz logged errors: {errors}"
    assert png.is_file() and png.stat().st_size > 20000, f"no screenshot at {png}"


def test_check_detects_a_broken_display(tmp_path: Path, ros_scene):
    """Control: an Axes display on a frame nobody publishes must be reported as Error."""
    text = (REPO / "rviz" / "localization.rviz").read_text()
    axes = ("  - Class: rviz/Axes\n    Enabled: true\n    Length: 1\n    Name: Broken axes\n    Radius: 0.1\n"
            "    Reference Frame: no_such_frame\n    Value: true\n")
    marker = "  Displays:\n"
    assert marker in text
    broken = tmp_path / "broken.rviz"
    broken.write_text(text.replace(marker, marker + axes, 1))
    displays, out = _run_rviz(broken, tmp_path / "broken.png", ros_scene)
    levels = {d[0]: d[2] for d in displays}
    assert levels.get("Broken axes", "").lower().startswith("error"), f"control not detected: {displays}\n{out[-2000:]}"
