"""The mapper calibrating the ring from rough values while mapping (calibration/extrinsics: rough):
MappingPipeline.calibrate, MapBuilder.recalibrate, the frames kept for it, the schema."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import with_overrides
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.pipeline import MappingPipeline, feed_ring_frame, ring_file_beside
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.schemas import MapperCalibrationParams, MapperConfig
from aruco_ring_localization.simulation.calibration_run import calibration_poses, rough_ring
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

RING = os.path.join(os.path.dirname(__file__), "..", "..", "config", "ring.yaml")


def _config(**calibration) -> MapperConfig:
    over = {"input.use_tf": True, "input.camera_info_fallback": True, "input.slop": 0.01}
    over.update({f"calibration.{k}": v for k, v in calibration.items()})
    return with_overrides(MapperConfig(), over)


def _lab(poses, seed=0):
    scene = Scene.default()
    true = perturb_ring(CameraRing.load(RING), seed=seed + 1)
    sim = RingSimulator(scene, true, pixel_noise=0.3, seed=seed)
    frames = [sim.observe(Scene.T_world_base(p), stamp=10.0 + 0.2 * k) for k, p in enumerate(poses)]
    return true, rough_ring(true, seed=seed + 5), frames


def test_rough_mode_calibrates_the_ring_and_the_map_builder_uses_it():
    st = Scene.default().mapping_stations
    true, rough, frames = _lab(calibration_poses(st[:1], turn_step_deg=10.0))
    pipe = MappingPipeline(_config(extrinsics="rough"), rough)
    assert not pipe.input.params.use_tf, "calibrating from rough values never takes tf's extrinsics"
    for f in frames:
        feed_ring_frame(pipe, f)
    assert len(pipe.calibration_stamps) == len(frames)
    assert all(np.allclose(o.T_base_cam, rough[o.camera].T_base_cam) for o in pipe.builder._obs)
    # Progress before the calibration: no map initialised through the rough values.
    assert pipe.format_summary().startswith("calibrating the ring from rough values")
    assert pipe.builder._init_cache is None
    cal = pipe.calibrate()
    assert pipe.calibration is cal
    G = geo.average_transforms([c.T_base_cam @ geo.inverse(cal.ring[c.name].T_base_cam) for c in true])
    for c in true:
        D = geo.inverse(c.T_base_cam) @ G @ pipe.ring[c.name].T_base_cam
        assert np.linalg.norm(D[:3, 3]) < 0.002 and np.degrees(geo.rotation_angle(D[:3, :3])) < 0.1, c.name
        assert np.allclose(pipe.builder.ring[c.name].T_base_cam, cal.ring[c.name].T_base_cam)
    # The observations added before the calibration now carry the calibrated extrinsics.
    assert pipe.builder._obs
    for o in pipe.builder._obs:
        assert np.allclose(o.T_base_cam, cal.ring[o.camera].T_base_cam), o.camera
    assert "markers mapped" in pipe.format_summary()
    # Calibrated again: from the rough values each time, the same answer.
    again = pipe.calibrate()
    for c in true:
        assert np.allclose(again.ring[c.name].T_base_cam, cal.ring[c.name].T_base_cam, atol=1e-9)


def test_calibrate_is_refused_when_the_mode_is_off():
    pipe = MappingPipeline(_config(), CameraRing.load(RING))
    assert pipe.rough_ring is None and pipe.input.params.use_tf
    feed_ring_frame(pipe, _lab([(5.5, 4.5, 0.0)])[2][0])
    assert pipe.calibration_stamps == [], "frames are kept for the calibration only in rough mode"
    with pytest.raises(ConfigError, match="calibration.extrinsics"):
        pipe.calibrate()


def test_the_frames_kept_stay_bounded_and_spread_over_the_whole_run():
    _, rough, frames = _lab([(5.5, 4.5, np.radians(4.0 * k)) for k in range(40)])
    pipe = MappingPipeline(_config(extrinsics="rough", keep_frames=8, max_frames=4), rough)
    for f in frames:
        feed_ring_frame(pipe, f)
    kept = pipe.calibration_stamps
    assert 4 <= len(kept) < 8, kept
    assert kept[0] == frames[0].stamp
    assert kept[-1] >= frames[-8].stamp, "the latest part of the run is kept too"
    steps = np.diff(kept)
    assert steps.max() <= 2.0 * steps.min() + 1e-9, f"uneven spacing {steps}"
    pipe.clear()
    assert pipe.calibration_stamps == []


@pytest.mark.parametrize("over, key", [
    ({"extrinsics": "drawing"}, "extrinsics"), ({"max_frames": 2}, "max_frames"), ({"keep_frames": 10, "max_frames": 20},
                                                                       "keep_frames")])
def test_bad_calibration_parameters_name_the_key(over, key):
    with pytest.raises(ConfigError) as info:
        MapperCalibrationParams(**over)
    assert key in str(info.value)


def test_the_ring_file_goes_beside_the_map():
    assert ring_file_beside("/data/hall.yaml") == "/data/hall_ring.yaml"
    assert ring_file_beside("/data/hall.yml") == "/data/hall_ring.yaml"
    assert ring_file_beside("/data/hall") == "/data/hall_ring.yaml"
