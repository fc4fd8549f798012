"""The ring calibration a map may carry (extrinsics refined while mapping) and its use."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap
from aruco_ring_localization.ring import CameraRing, apply_refined_extrinsics

RING = os.path.join(os.path.dirname(__file__), "..", "..", "config", "ring.yaml")


def _map_with_calibration(ring: CameraRing) -> MarkerMap:
    refined = {c.name: geo.se3_perturb(c.T_base_cam, [0.0, 0.0, 0.003, 0.001, -0.002, 0.0]) for c in ring}
    return MarkerMap([MarkerEntry(7, geo.transform_from_se2(1.0, 2.0, 0.3, 1.0), 0.2)],
                     reference_marker=7, ring_extrinsics=refined)


def test_ring_calibration_round_trips_through_the_map_file(tmp_path):
    ring = CameraRing.load(RING)
    m = _map_with_calibration(ring)
    path = str(tmp_path / "map.yaml")
    m.save(path)
    loaded = MarkerMap.load(path)
    assert sorted(loaded.ring_extrinsics) == ring.names
    for name, T in m.ring_extrinsics.items():
        err = np.abs(loaded.ring_extrinsics[name] - T).max()
        assert err < 1e-9, f"{name}: extrinsics changed by {err:.2e} through save/load"
    assert loaded.ring_base_frame == "base_link"


def test_a_map_without_calibration_has_none(tmp_path):
    path = str(tmp_path / "map.yaml")
    MarkerMap([MarkerEntry(7, np.eye(4), 0.2)]).save(path)
    assert "ring_calibration" not in open(path, encoding="utf-8").read()
    assert MarkerMap.load(path).ring_extrinsics == {}


def test_apply_refined_extrinsics_replaces_only_the_given_cameras():
    ring = CameraRing.load(RING)
    m = _map_with_calibration(ring)
    only_two = {k: m.ring_extrinsics[k] for k in ("cam0", "cam5")}
    out = apply_refined_extrinsics(ring, only_two, "base_link")
    for c in out:
        expected = only_two.get(c.name, ring[c.name].T_base_cam)
        assert np.allclose(c.T_base_cam, expected), c.name
        assert c.model is ring[c.name].model


def test_apply_refined_extrinsics_rejects_other_base_frames_and_unknown_cameras():
    ring = CameraRing.load(RING)
    with pytest.raises(ConfigError, match="ring_calibration.base_frame"):
        apply_refined_extrinsics(ring, {"cam0": np.eye(4)}, "base_footprint", source="m.yaml")
    with pytest.raises(ConfigError, match=r"m.yaml.*ring_calibration.cameras.*cam9"):
        apply_refined_extrinsics(ring, {"cam9": np.eye(4)}, "base_link", source="m.yaml")


@pytest.mark.parametrize("node, key", [
    ("not a mapping", "ring_calibration"),
    ({"cameras": {}}, "ring_calibration"),
    ({"base_frame": "", "cameras": {"cam0": {"translation": [0, 0, 0], "rotation": [0, 0, 0, 1]}}},
     "ring_calibration.base_frame"),
    ({"cameras": {"cam0": {"translation": [0, 0], "rotation": [0, 0, 0, 1]}}}, "ring_calibration.cameras.cam0"),
    ({"cameras": {"cam0": {"translation": [0, 0, 0], "rotation": [0, 0, 0, 3]}}}, "ring_calibration.cameras.cam0"),
])
def test_bad_ring_calibration_names_file_and_key(tmp_path, node, key):
    data = MarkerMap([MarkerEntry(7, np.eye(4), 0.2)]).to_dict()
    data["ring_calibration"] = node
    with pytest.raises(ConfigError) as info:
        MarkerMap.from_dict(data, source="hall.yaml")
    assert "hall.yaml" in str(info.value) and key in str(info.value), str(info.value)
