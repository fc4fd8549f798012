"""MapBuilder with survey measurements (distances, planes): the map file's record and the save check."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization.anchors import anchors_from_dict, noisy_anchors
from aruco_ring_localization.errors import ConfigError, MapSanityError
from aruco_ring_localization.mapping import MapBuilder
from aruco_ring_localization.marker_map import MarkerMap, check_map
from aruco_ring_localization.markers import MarkerSizes, marker_corners


def _corner(T, c):
    return T[:3, :3] @ marker_corners(0.2)[c] + T[:3, 3]


def _distances(truth, pairs, std=0.0005, scale=1.0):
    return [{"from": {"marker": a, "corner": 0}, "to": {"marker": b, "corner": 2},
             "distance": scale * float(np.linalg.norm(_corner(truth.T_map_marker(a), 0)
                                                      - _corner(truth.T_map_marker(b), 2))), "std": std}
            for a, b in pairs]


def _build(ring, frames, anchors):
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors)
    for f in frames:
        b.add_frame(f)
    return b


def _far_pair(truth):
    ids = truth.ids
    P = {m: truth.T_map_marker(m)[:3, 3] for m in ids}
    return max(((a, b) for a in ids for b in ids if a < b), key=lambda p: float(np.linalg.norm(P[p[0]] - P[p[1]])))


def test_measurements_only_keep_the_reference_frame_and_are_recorded(ring, frames, truth, tmp_path):
    a, b = _far_pair(truth)
    survey = anchors_from_dict({"distances": _distances(truth, [(a, b)])}, source="tape.yaml")
    builder = _build(ring, frames, survey)
    assert builder.anchors is None and builder.measurements is not None
    m = builder.save_map(str(tmp_path / "map.yaml"))
    assert m.anchors is None and m.reference_marker is not None          # the frame stays the marker's
    rec = MarkerMap.load(str(tmp_path / "map.yaml")).quality["survey_measurements"]
    (d,) = rec["distances"]
    assert d["from"] == {"marker": a, "corner": 0} and d["to"] == {"marker": b, "corner": 2}
    mapped = float(np.linalg.norm(_corner(m[a].T_map_marker, 0) - _corner(m[b].T_map_marker, 2)))
    assert d["mapped_distance"] == pytest.approx(mapped, abs=1e-9)
    assert d["residual_mm"] == pytest.approx(1000 * (mapped - d["measured"]), abs=1e-6)
    assert d["residual_sigmas"] < 3.0, d


def test_a_mistyped_distance_stops_the_save(ring, frames, truth, tmp_path):
    """A distance 5 % off its true length: the images disagree with it far beyond 5 sigma; the
    save is refused naming the measurement, nothing is written."""
    a, b = _far_pair(truth)
    survey = anchors_from_dict({"distances": _distances(truth, [(a, b)], scale=1.05)}, source="tape.yaml")
    builder = _build(ring, frames, survey)
    path = tmp_path / "map.yaml"
    with pytest.raises(MapSanityError) as exc:
        builder.save_map(str(path))
    assert "distances[0]" in str(exc.value) and "tape.yaml" in str(exc.value)
    assert not path.exists()
    # The check is the map's own (check_map): a direct MarkerMap.save refuses it too.
    m = builder.build("refined")
    assert any(p.startswith("measurements: distances[0]") for p in check_map(m))
    with pytest.raises(MapSanityError):
        m.save(str(path))
    assert not path.exists()


def test_a_plane_with_anchors_is_recorded_and_a_plane_without_is_refused(ring, frames, truth, tmp_path):
    ids = truth.ids
    anchors = noisy_anchors({m: truth.T_map_marker(m) for m in ids}, [ids[0], ids[len(ids) // 2], ids[-1]], 0.001,
                            seed=0).to_dict()["anchors"]
    # A plane through marker ids[1]'s corners in the truth (the survey frame): its normal is the
    # marker's own z, its offset that of its centre.
    T = truth.T_map_marker(ids[1])
    n = T[:3, 2]
    plane = {"markers": [ids[1]], "normal": [float(v) for v in n], "distance": float(n @ T[:3, 3]), "std": 0.002}
    survey = anchors_from_dict({"anchors": anchors, "planes": [plane]}, source="plate.yaml")
    m = _build(ring, frames, survey).save_map(str(tmp_path / "map.yaml"))
    (p,) = m.quality["survey_measurements"]["planes"]
    assert p["markers"] == [ids[1]] and p["residual_sigmas"] < 5.0 and "rms_mm" in p
    with pytest.raises(ConfigError, match="plane"):
        anchors_from_dict({"planes": [plane]}, source="plate.yaml")


def test_the_mapper_reads_measurements_from_its_anchors_file(tmp_path):
    """``map/anchors_file`` (build-map --anchors) with distances only: the pipeline's MapBuilder
    keeps the reference frame and the distances; a plane without anchors stops it at start."""
    from aruco_ring_localization.config import with_overrides
    from aruco_ring_localization.pipeline import MappingPipeline
    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.schemas import MapperConfig
    from helpers import RING_YAML

    tape = tmp_path / "tape.yaml"
    tape.write_text("distances: [{from: {marker: 1, corner: 0}, to: {marker: 2, corner: 3}, distance: 4.2, "
                    "std: 0.002}]\n")
    ring = CameraRing.load(str(RING_YAML))
    offline = {"input.use_tf": False, "input.camera_info_fallback": True, "map.anchors_file": str(tape)}
    pipe = MappingPipeline(with_overrides(MapperConfig(), offline), ring)
    assert pipe.builder.anchors is None
    (d,) = pipe.builder.measurements.distances
    assert (d.a.corner, d.b.corner, d.distance) == (0, 3, 4.2)
    tape.write_text("planes: [{markers: [1, 2], normal: [0, 0, 1], distance: 0, std: 0.01}]\n")
    with pytest.raises(ConfigError) as err:
        MappingPipeline(with_overrides(MapperConfig(), offline), ring)
    assert err.value.key == "planes[0]" and str(tape) in str(err.value)
