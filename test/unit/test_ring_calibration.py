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


# --- the covariance of the refined extrinsics ------------------------------------------------

def _covariance(n: int, seed: int = 0) -> np.ndarray:
    A = np.random.default_rng(seed).normal(0.0, 1e-3, (6 * n, 6 * n))
    return A @ A.T


def test_ring_covariance_round_trips_through_the_map_file(tmp_path):
    ring = CameraRing.load(RING)
    m = _map_with_calibration(ring)
    m.ring_covariance_cameras = list(ring.names)
    m.ring_extrinsics_covariance = _covariance(len(ring))
    path = str(tmp_path / "map.yaml")
    m.save(path)
    loaded = MarkerMap.load(path)
    assert loaded.ring_covariance_cameras == ring.names
    rel = np.abs(loaded.ring_extrinsics_covariance - m.ring_extrinsics_covariance).max() \
        / np.abs(m.ring_extrinsics_covariance).max()
    assert rel < 1e-8, f"covariance changed by {rel:.1e} (relative) through save/load (9 digits written)"
    assert MarkerMap.load(path).ring_extrinsics_covariance is not None
    plain = _map_with_calibration(ring)
    plain.save(path)
    assert MarkerMap.load(path).ring_extrinsics_covariance is None


@pytest.mark.parametrize("node, needle", [
    ("not a mapping", "ring_calibration.covariance"),
    ({"cameras": ["cam0", "cam9"], "matrix": np.eye(12).tolist()}, "ring_calibration.covariance.cameras"),
    ({"cameras": ["cam0", "cam0"], "matrix": np.eye(12).tolist()}, "ring_calibration.covariance.cameras"),
    ({"cameras": ["cam0"], "matrix": np.eye(12).tolist()}, "ring_calibration.covariance.matrix"),
    ({"cameras": ["cam0"], "matrix": [["a"] * 6] * 6}, "ring_calibration.covariance.matrix"),
    ({"cameras": ["cam0"], "matrix": (-np.eye(6)).tolist()}, "negative eigenvalue"),
])
def test_bad_ring_covariance_names_file_and_key(node, needle):
    ring = CameraRing.load(RING)
    data = _map_with_calibration(ring).to_dict()
    data["ring_calibration"]["covariance"] = node
    with pytest.raises(ConfigError) as info:
        MarkerMap.from_dict(data, source="hall.yaml")
    assert "hall.yaml" in str(info.value) and needle in str(info.value), str(info.value)


def test_mapping_stores_the_adjustments_covariance_in_optical_frames():
    """The bundle adjustment's (w, dt) of camera c, in the base frame, is D = (R_c^T w, R_c^T dt)
    in the camera's optical frame (T_base_cam_true = T_base_cam D)."""
    from aruco_ring_localization.bundle_adjustment import camera_cov_in_optical_frames

    ring = CameraRing.load(RING)
    T = np.stack([c.T_base_cam for c in ring.cameras[:2]])
    C = _covariance(2, seed=1)
    out = camera_cov_in_optical_frames(C, T)
    rng = np.random.default_rng(2)
    x = rng.multivariate_normal(np.zeros(12), C, size=4)
    for s in x:  # the same motion both ways, to first order
        for k in range(2):
            w, dt = s[6 * k:6 * k + 3] * 1e-3, s[6 * k + 3:6 * k + 6] * 1e-3
            moved = geo.make_transform(geo.rotation_from_rvec(w) @ T[k][:3, :3], T[k][:3, 3] + dt)
            D = geo.inverse(T[k]) @ moved
            d = np.r_[geo.rvec_from_rotation(D[:3, :3]), D[:3, 3]] / 1e-3
            R = T[k][:3, :3].T
            assert np.allclose(d, np.r_[R @ s[6 * k:6 * k + 3], R @ s[6 * k + 3:6 * k + 6]], atol=1e-5)
    assert out.shape == (12, 12) and np.allclose(out, out.T)
    R0, R1 = T[0][:3, :3].T, T[1][:3, :3].T
    assert np.allclose(out[:3, 6:9], R0 @ C[:3, 6:9] @ R1.T), "cross-camera block not carried"
