"""RingInputCore (the logic of ros/ring_input.py) and ros/params.py's coercion, without ROS."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.detections import MarkerObservation
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.detections import SKIP_NO_CAMERA_INFO, SKIP_NO_EXTRINSICS, RingInputCore

RING_FILE = Path(__file__).resolve().parents[2] / "config" / "ring.yaml"


@pytest.fixture(scope="module")
def ring() -> CameraRing:
    return CameraRing.load(str(RING_FILE))


def _square(cx=640.0, cy=480.0, s=40.0) -> np.ndarray:
    return np.array([[cx - s, cy - s], [cx + s, cy - s], [cx + s, cy + s], [cx - s, cy + s]])


def test_camera_skipped_without_camera_info_unless_fallback(ring):
    core = RingInputCore(ring, ["cam0"], extrinsics_from_ring=True)
    frames, reason, _ = core.add_detections("cam0", 1.0, [MarkerObservation(1, _square())], now=0.0)
    assert reason == SKIP_NO_CAMERA_INFO and frames == []
    assert core.skipped["cam0"][SKIP_NO_CAMERA_INFO] == 1
    core_fb = RingInputCore(ring, ["cam0"], extrinsics_from_ring=True, camera_info_fallback=True)
    frames, reason, _ = core_fb.add_detections("cam0", 1.0, [MarkerObservation(1, _square())], now=0.0)
    assert reason is None and len(frames) == 1, f"reason={reason}, {len(frames)} frames"
    assert frames[0].cameras["cam0"].model is ring["cam0"].model


def test_camera_skipped_until_extrinsics_then_ring_updated(ring):
    core = RingInputCore(ring, ["cam0", "cam1"], camera_info_fallback=True)
    _, reason, _ = core.add_detections("cam0", 1.0, [], now=0.0)
    assert reason == SKIP_NO_EXTRINSICS
    T = geo.compose(ring["cam0"].T_base_cam, geo.make_transform(t=[0.001, 0.0, 0.0]))
    core.set_extrinsics("cam0", T)
    assert np.allclose(core.ring["cam0"].T_base_cam, T)
    assert np.allclose(core.ring["cam1"].T_base_cam, ring["cam1"].T_base_cam)
    _, reason, _ = core.add_detections("cam0", 1.0, [], now=0.0)
    assert reason is None


def test_silent_camera_does_not_stall_and_is_reported(ring):
    core = RingInputCore(ring, ["cam0", "cam1"], timeout=0.2, camera_info_fallback=True, extrinsics_from_ring=True)
    frames, _, _ = core.add_detections("cam0", 5.0, [MarkerObservation(3, _square())], now=10.0)
    assert frames == []
    assert core.poll(10.1) == []
    out = core.poll(10.25)
    assert len(out) == 1 and out[0].missing == ["cam1"], f"got {out}"
    assert core.silent_cameras(10.25, silence=0.5) == ["cam1"]


def test_malformed_detections_dropped_and_counted(ring):
    core = RingInputCore(ring, ["cam0"], camera_info_fallback=True, extrinsics_from_ring=True, ignore_ids=[9])
    bad = _square()
    bad[2, 0] = np.nan
    obs = [MarkerObservation(1, bad), MarkerObservation(2, _square(300)), MarkerObservation(2, _square(900)),
           MarkerObservation(9, _square(500)), MarkerObservation(4, _square(200, 200))]
    frames, _, dropped = core.add_detections("cam0", 1.0, obs, now=0.0)
    kept = [o.marker_id for o in frames[0].cameras["cam0"].observations]
    assert kept == [4], f"kept {kept}"
    assert dropped == {"non-finite": 1, "duplicate id": 2, "ignored": 1}, dropped
    assert core.rejected["cam0"] == dropped


def test_unknown_camera_rejected_at_construction(ring):
    with pytest.raises(ValueError, match="not in the ring"):
        RingInputCore(ring, ["cam9"])


@dataclass(frozen=True)
class _Params:
    map_file: str = field(default="", metadata={"doc": "where to save"})
    slop: float = 0.03
    count: int = 3
    enabled: bool = True
    cameras: tuple = ()


def test_params_coercion_and_errors():
    from aruco_ring_localization.ros.params import describe, params_from_dict

    p = params_from_dict(_Params, {"slop": 1, "cameras": "cam0, cam1", "enabled": False})
    assert p.slop == 1.0 and isinstance(p.slop, float)
    assert p.cameras == ("cam0", "cam1") and p.enabled is False and p.count == 3
    with pytest.raises(ConfigError, match="enabled"):
        params_from_dict(_Params, {"enabled": "false"})
    with pytest.raises(ConfigError, match="count"):
        params_from_dict(_Params, {"count": 2.5})
    assert describe(_Params)["map_file"] == "where to save"
