"""A real recording end to end: TagSLAM's test_8 (a handheld rig of 4 fisheye cameras, 160 frames,
31 tags) mapped and localized by the package, against TagSLAM's answer (test/data/tagslam/SOURCE.txt).

The tolerances are the figures measured on this recording (stated beside each) with a margin;
TagSLAM's solution is a peer system's estimate, not ground truth.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.evaluation.maps import map_error
from aruco_ring_localization.importers import read_rig, read_tagslam_tags
from aruco_ring_localization.localization import LocalizationParams, RingLocalizer
from aruco_ring_localization.mapping import MapBuilder, MappingOptions
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import apply_refined_extrinsics

pytest.importorskip("rosbag")

REPO = Path(__file__).resolve().parents[2]
REC = REPO / "test" / "data" / "tagslam" / "test_8"
sys.path.insert(0, str(REPO / "bench"))


@pytest.fixture(scope="module")
def rec():
    from tagslam_reference import read_tum_poses, ring_frames

    rig = read_rig(str(REC / "cameras.yaml"), camera_poses=str(REC / "camera_poses.yaml"))
    ring = rig.ring()
    tags = read_tagslam_tags(str(REC / "tagslam.yaml"))
    frames = ring_frames(str(REC / "tag_detections.bag"), ring)
    stamps, poses = read_tum_poses(str(REC / "rig_poses.tum"))
    return dict(ring=ring, sizes=tags.marker_sizes(), frames=frames, truth=MarkerMap.load(str(REC / "tags.yaml")),
                reference={int(round(t * 1e6)): T for t, T in zip(stamps, poses)})


@pytest.fixture(scope="module")
def built(rec):
    b = MapBuilder(rec["ring"], rec["sizes"], options=MappingOptions(frame="marker"))
    for f in rec["frames"]:
        b.add_frame(f)
    return b, b.build()


def _localize(ring, marker_map, frames, reference, T_ref_map=np.eye(4)):
    loc = RingLocalizer(ring, marker_map, LocalizationParams(fusion="joint"))
    pos, rot = [], []
    for f in frames:
        T_ref = reference.get(int(round(f.stamp * 1e6)))
        res = loc.process(f)
        if T_ref is None or not res.ok:
            continue
        dp, dr = geo.pose_distance(T_ref, T_ref_map @ res.T_map_base)
        pos.append(1000.0 * dp)
        rot.append(np.degrees(dr))
    return np.array(pos), np.array(rot)


def test_the_handheld_rig_is_mapped_like_tagslam(built, rec, tmp_path):
    b, m = built
    s = b.summary()
    assert s["station_model"] == "se3" and s["rejected"] == {} and s["unlinked"] == []
    err = map_error(m, rec["truth"], best_fit=True)
    assert err["missing"] == [] and err["n"] == 31, err["missing"]
    # Measured: 1.22 mm RMS, 3.70 mm max, rotations 0.021 deg median; limits 1.5x.
    assert err["position_rms_mm"] < 1.8 and err["position_max_mm"] < 5.5, (err["position_rms_mm"], err["position_max_mm"])
    assert np.median([v[1] for v in err["per_marker"].values()]) < 0.032
    # Reprojection 0.56 px RMS (TagSLAM's own solution: 0.79 px on the same detections).
    assert m.quality["reprojection_rms_px"] < 0.8
    m.save(str(tmp_path / "map.yaml"), b.options.sanity)     # passes the sanity checks


def test_localization_on_tagslams_map_and_on_ours(built, rec):
    # On TagSLAM's map with TagSLAM's extrinsics, one estimate per frame (no filter): measured
    # median 1.98 mm, p95 9.3 mm, max 29.5 mm, rotation max 0.79 deg over 158 frames; limits 1.5x
    # (the target, a 1.5 mm median, is not met here: docs/benchmarks.md, "Real recordings").
    pos, rot = _localize(rec["ring"], rec["truth"], rec["frames"], rec["reference"])
    assert len(pos) >= 150
    assert np.median(pos) < 3.0 and np.percentile(pos, 95) < 14.0 and rot.max() < 1.2, \
        (np.median(pos), np.percentile(pos, 95), rot.max())
    # On our map with its refined extrinsics, in TagSLAM's frame by the map's best-fit alignment.
    b, m = built
    T = map_error(m, rec["truth"], best_fit=True)["T_truth_est"]
    ring = apply_refined_extrinsics(rec["ring"], m.ring_extrinsics, m.ring_base_frame)
    pos2, rot2 = _localize(ring, m, rec["frames"], rec["reference"], T)
    # Measured: median 2.10 mm, p95 11.7 mm, rotation max 0.81 deg; limits 1.5x.
    assert len(pos2) >= 150
    assert np.median(pos2) < 3.2 and np.percentile(pos2, 95) < 17.5 and rot2.max() < 1.25, \
        (np.median(pos2), np.percentile(pos2, 95), rot2.max())


def test_planar_stations_are_what_broke_this_recording(rec):
    """The rig frame is camera 0's optical frame: stations that move in its x-y plane and turn
    about its optical axis cannot follow a handheld rig. Forced on, the planar initialisation
    rejects 30 of the 31 tags as "inconsistent between stations" (metres apart) and reprojects at
    thousands of pixels (measured 4,996 px against 1.50 px for the SE(3) initialisation): the
    failure users met on such a rig."""
    forced = MapBuilder(rec["ring"], rec["sizes"], method="paper",
                        options=MappingOptions(frame="marker", planar_max_tilt_deg=180.0, planar_max_height_change=99.0))
    se3 = MapBuilder(rec["ring"], rec["sizes"], method="paper", options=MappingOptions(frame="marker", planar=False))
    for f in rec["frames"]:
        forced.add_frame(f)
        se3.add_frame(f)
    assert forced.summary()["station_model"] == "planar" and se3.summary()["station_model"] == "se3"
    bad, good = forced.build(), se3.build()
    assert len(good) == 31 and len(bad) < 5, (len(good), len(bad))
    assert all("inconsistent between stations" in why for why in forced.summary()["rejected"].values())
    assert bad.quality["reprojection_rms_px"] > 100 * good.quality["reprojection_rms_px"], \
        (bad.quality["reprojection_rms_px"], good.quality["reprojection_rms_px"])


def _track(ring, marker_map, frames, reference, model):
    from aruco_ring_localization.config import with_overrides
    from aruco_ring_localization.pipeline import LocalizationPipeline, feed_ring_frame
    from aruco_ring_localization.schemas import LocalizerConfig

    config = with_overrides(LocalizerConfig(), {"input.use_tf": False, "input.camera_info_fallback": True,
                                                "estimator.fusion": "joint", "input.slop": 0.005,
                                                "filter.model": model})
    pipeline = LocalizationPipeline(config, ring, marker_map)
    pos, rot = [], []
    for f in frames:
        for out in feed_ring_frame(pipeline, f):
            T_ref = reference.get(int(round(out.stamp * 1e6)))
            if T_ref is not None:
                dp, dr = geo.pose_distance(T_ref, out.T_map_base)
                pos.append(1000.0 * dp)
                rot.append(np.degrees(dr))
    return np.array(pos), np.array(rot)


def test_the_6dof_tracker_follows_the_handheld_rig_without_a_flip(rec):
    """filter/model 6dof on TagSLAM's map: every frame out, none more than 10 deg or 0.5 m off, the
    filtered error as small as the per-frame one (the planar filter it replaces outputs x, y, yaw
    only: its roll and pitch would be tens of degrees off on this rig)."""
    pos, rot = _track(rec["ring"], rec["truth"], rec["frames"], rec["reference"], "6dof")
    # Measured (2026-12-02): 158 of 158 frames, median 2.35 mm, max 26.5 mm, rotation max 0.32 deg;
    # limits about 1.5x (the per-frame estimate: median 1.98 mm, rotation max 0.79 deg).
    assert len(pos) >= 155
    assert not np.any((rot > 10.0) | (pos > 500.0))
    assert np.median(pos) < 3.5 and pos.max() < 40.0 and rot.max() < 0.5, (np.median(pos), pos.max(), rot.max())
