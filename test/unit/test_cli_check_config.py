"""Unit tests of ``aruco_ring check-config``: exit codes, the summary, errors naming file and key."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.cli import main
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap

from helpers import CONFIG, REPO, RING_YAML, write_text


def _broken_ring(tmp_path, mutate) -> str:
    data = yaml.safe_load(RING_YAML.read_text())
    for cam in data["cameras"]:
        cam["camera_info"] = str(CONFIG / cam["camera_info"])
    mutate(data)
    return str(write_text(tmp_path, "ring.yaml", yaml.safe_dump(data)))


def _saved_map(tmp_path) -> str:
    entries = [MarkerEntry(i, geo.transform_from_se2(i, -i, 0.1 * i, z=1.2), 0.2, np.full(3, 0.002), np.zeros(3), 40 + i)
               for i in (3, 7, 11)]
    path = str(tmp_path / "map.yaml")
    MarkerMap(entries, reference_marker=3, method="refined").save(path)
    return path


def test_good_ring_exits_0_with_a_summary(capsys):
    assert main(["check-config", "--ring", str(RING_YAML)]) == 0
    out = capsys.readouterr().out
    assert f"ring {RING_YAML}: OK" in out
    assert "8 cameras, base frame base_link" in out
    for k in range(8):
        assert f"cam{k}_optical_frame" in out
    assert out.count("HFOV") == 8 and out.count("overlap") == 8
    assert "ERROR" not in out


def test_broken_ring_exits_1_naming_file_and_key(tmp_path, capsys):
    def mutate(data):
        data["cameras"][3]["T_base_camera"]["rotation"] = [0.0, 0.0, 0.0, 3.0]
    path = _broken_ring(tmp_path, mutate)
    assert main(["check-config", "--ring", path]) == 1
    out = capsys.readouterr().out
    assert "ERROR" in out and path in out and "cameras[3].T_base_camera" in out, out


def test_missing_ring_file_exits_1(tmp_path, capsys):
    path = str(tmp_path / "none.yaml")
    assert main(["check-config", "--ring", path]) == 1
    out = capsys.readouterr().out
    assert path in out and "not found" in out, out


def test_with_a_saved_map(tmp_path, capsys):
    map_path = _saved_map(tmp_path)
    assert main(["check-config", "--ring", str(RING_YAML), "--map", map_path]) == 0
    out = capsys.readouterr().out
    assert f"map {map_path}: OK, 3 markers in frame 'map', reference marker 3" in out, out
    assert out.count("  marker ") == 3 and "2.0 mm" in out, out


def test_with_a_broken_map_exits_1(tmp_path, capsys):
    map_path = _saved_map(tmp_path)
    data = yaml.safe_load(open(map_path))
    data["markers"][1]["size"] = -0.2
    write_text(tmp_path, "map.yaml", yaml.safe_dump(data))
    assert main(["check-config", "--ring", str(RING_YAML), "--map", map_path]) == 1
    out = capsys.readouterr().out
    assert f"ring {RING_YAML}: OK" in out  # the ring is still checked and summarised
    assert "map: ERROR" in out and map_path in out and "markers[1].size" in out, out


def test_both_broken_report_both(tmp_path, capsys):
    ring_path = _broken_ring(tmp_path, lambda d: d.pop("cameras"))
    map_path = write_text(tmp_path, "map.yaml", "")
    assert main(["check-config", "--ring", ring_path, "--map", str(map_path)]) == 1
    out = capsys.readouterr().out
    assert "ring: ERROR" in out and "'cameras'" in out and "map: ERROR" in out and str(map_path) in out, out


def test_script_runs_as_a_program(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    ok = subprocess.run([sys.executable, str(REPO / "scripts" / "aruco_ring"), "check-config", "--ring", str(RING_YAML)],
                        capture_output=True, text=True, env=env, timeout=60)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "8 cameras" in ok.stdout
    path = _broken_ring(tmp_path, lambda d: d["cameras"][0].pop("name"))
    bad = subprocess.run([sys.executable, str(REPO / "scripts" / "aruco_ring"), "check-config", "--ring", path],
                         capture_output=True, text=True, env=env, timeout=60)
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert path in bad.stdout and "cameras[0].name" in bad.stdout, bad.stdout


def test_a_map_with_surveyed_only_markers_says_which(tmp_path, capsys):
    entries = [MarkerEntry(i, geo.transform_from_se2(i, -i, 0.1 * i, z=1.2), 0.2, np.full(3, 0.002), np.zeros(3),
                           0 if i == 7 else 40, surveyed_only=(i == 7)) for i in (3, 7, 11)]
    path = str(tmp_path / "map.yaml")
    MarkerMap(entries, reference_marker=3, method="refined").save(path)
    assert main(["check-config", "--ring", str(RING_YAML), "--map", path]) == 0
    out = capsys.readouterr().out
    assert "surveyed only (never detected while mapping" in out and ": [7]" in out, out
    assert out.count("surveyed only\n") == 1 and out.count("40 observations") == 2, out
