"""MapBuilder with a surveyed frame (anchors): the strict error, the map file, the sanity check."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization.anchors import Anchor, AnchorSet, noisy_anchors
from aruco_ring_localization.errors import MapSanityError
from aruco_ring_localization.evaluation.maps import map_error
from aruco_ring_localization.mapping import MapBuilder, MappingOptions
from aruco_ring_localization.marker_map import MarkerMap, check_map
from aruco_ring_localization.markers import MarkerSizes


def _survey(truth, ids, std=0.001, seed=0):
    return noisy_anchors({m: truth.T_map_marker(m) for m in truth.ids}, ids, std, seed=seed, source="survey.yaml")


def _build(ring, frames, anchors, method="refined"):
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors)
    for f in frames:
        b.add_frame(f)
    return b.build(method)


def _spread_ids(truth, n=3):
    return [truth.ids[round(k * (len(truth.ids) - 1) / (n - 1))] for k in range(n)] if n > 1 else truth.ids[:1]


def test_surveyed_frame_beats_the_reference_marker_in_the_strict_convention(ring, frames, truth):
    ref_map = _build(ring, frames, None)
    surveyed = _build(ring, frames, _survey(truth, _spread_ids(truth)))
    ref_err, err = map_error(ref_map, truth), map_error(surveyed, truth)
    assert surveyed.frame_convention == "survey" and surveyed.reference_marker is None
    assert surveyed.anchors["kind"] == "points"
    assert err["n"] == len(truth)
    # The frame no longer rests on one marker's heading: the strict error drops to near the shape's.
    fit = map_error(surveyed, truth, best_fit=True)
    assert err["position_rms_mm"] < 0.5 * ref_err["position_rms_mm"], \
        f"strict RMS {err['position_rms_mm']:.2f} mm surveyed vs {ref_err['position_rms_mm']:.2f} mm reference"
    assert err["position_rms_mm"] < fit["position_rms_mm"] + 1.0, \
        f"strict {err['position_rms_mm']:.2f} mm vs best fit {fit['position_rms_mm']:.2f} mm"
    sig = [p["residual_sigmas"] for p in surveyed.anchors["points"]]
    assert len(sig) == 3 and max(sig) < 3.0, f"anchor residuals (sigmas) {sig}"
    assert check_map(surveyed) == []


def test_two_anchors_keep_the_robot_level(ring, frames, truth):
    ref_map = _build(ring, frames, None)
    surveyed = _build(ring, frames, _survey(truth, _spread_ids(truth, 2)))
    assert surveyed.anchors["kind"] == "points_level"
    err, ref_err = map_error(surveyed, truth), map_error(ref_map, truth)
    assert err["position_rms_mm"] < ref_err["position_rms_mm"], \
        f"strict RMS {err['position_rms_mm']:.2f} mm with 2 anchors vs {ref_err['position_rms_mm']:.2f} mm reference"
    z = np.array([e.T_map_marker[2, 3] - truth.T_map_marker(e.marker_id)[2, 3] for e in surveyed])
    assert np.max(np.abs(z)) < 0.005, f"height errors {np.round(1000 * z, 2)} mm: the plane tilted"


def test_paper_map_is_fitted_to_the_anchors(ring, frames, truth):
    paper_ref = _build(ring, frames, None, "paper")
    paper = _build(ring, frames, _survey(truth, _spread_ids(truth)), "paper")
    assert paper.frame_convention == "survey"
    assert map_error(paper, truth)["position_rms_mm"] < map_error(paper_ref, truth)["position_rms_mm"]


def test_map_file_round_trip_keeps_the_anchors(ring, frames, truth, tmp_path):
    m = _build(ring, frames, _survey(truth, _spread_ids(truth)))
    path = tmp_path / "map.yaml"
    m.save(str(path))
    back = MarkerMap.load(str(path))
    assert back.frame_convention == "survey" and back.reference_marker is None
    assert back.anchors["kind"] == m.anchors["kind"] and back.anchors["source"] == "survey.yaml"
    for a, b in zip(m.anchors["points"], back.anchors["points"]):
        assert a["marker"] == b["marker"] and np.allclose(a["residual"], b["residual"]) \
            and np.allclose(a["surveyed"], b["surveyed"])
    assert map_error(back, truth)["position_rms_mm"] == pytest.approx(map_error(m, truth)["position_rms_mm"])


def test_a_mistyped_survey_value_stops_the_save(ring, frames, truth, tmp_path):
    """One anchor 5 cm off (a typing error): the map fits the images, its residual is many sigma and
    the map is not written (MapSanityError naming the marker and the anchors file)."""
    good = _survey(truth, _spread_ids(truth, 4))
    a = good.anchors[2]
    bad = AnchorSet(good.anchors[:2] + [Anchor(a.marker_id, a.position + [0.05, 0.0, 0.0], a.position_std)]
                    + good.anchors[3:], source="survey.yaml")
    m = _build(ring, frames, bad)
    path = tmp_path / "map.yaml"
    with pytest.raises(MapSanityError) as err:
        m.save(str(path))
    assert f"marker {a.marker_id}" in str(err.value) and "survey.yaml" in str(err.value), str(err.value)
    assert not path.exists()


def test_too_few_surveyed_markers_seen_says_which(ring, frames, truth):
    """Only one surveyed marker is in the map (the other ids are not in the lab): no frame yet, and
    the error names the anchors file and the markers it still needs."""
    one = _survey(truth, _spread_ids(truth, 2))
    a = one.anchors[0]
    anchors = AnchorSet([a, Anchor(9999, a.position + 1.0, a.position_std)], source="survey.yaml")
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors)
    for f in frames[:3]:
        b.add_frame(f)
    from aruco_ring_localization.errors import ArucoRingError

    with pytest.raises(ArucoRingError) as err:
        b.build("paper")
    assert "survey.yaml" in str(err.value) and "9999" in str(err.value), str(err.value)


def test_both_solvers_give_the_same_surveyed_map(ring, frames, truth):
    import dataclasses

    from aruco_ring_localization.mapping import MappingOptions

    maps = {}
    for solver in ("lm", "trf"):
        o = MappingOptions()
        o = dataclasses.replace(o, ba=dataclasses.replace(o.ba, solver=solver))
        b = MapBuilder(ring, MarkerSizes(0.2), options=o, anchors=_survey(truth, _spread_ids(truth)))
        for f in frames:
            b.add_frame(f)
        maps[solver] = b.build()
    d = max(float(np.linalg.norm(maps["lm"].T_map_marker(i)[:3, 3] - maps["trf"].T_map_marker(i)[:3, 3]))
            for i in maps["lm"].ids)
    assert d < 1e-4, f"lm and trf surveyed maps differ by {1000 * d:.3f} mm"
    assert map_error(maps["trf"], truth)["position_rms_mm"] < map_error(_build(ring, frames, None), truth)[
        "position_rms_mm"]


def _without(frames, marker_id):
    """The frames with every detection of ``marker_id`` removed (a marker the recording never sees)."""
    import dataclasses

    return [dataclasses.replace(f, cameras={c: dataclasses.replace(cf, observations=[o for o in cf.observations
                                                                                   if o.marker_id != marker_id])
                                            for c, cf in f.cameras.items()}) for f in frames]


def _with_unseen(truth, unseen_full, unseen_position, std=0.002, rot_std=0.01):
    """Three spread position anchors plus, for markers no frame shows, one with its full (true) pose
    and one with its position only."""
    base = _survey(truth, [m for m in _spread_ids(truth) if m not in (unseen_full, unseen_position)])
    T, P = truth.T_map_marker(unseen_full), truth.T_map_marker(unseen_position)
    extra = [Anchor(unseen_full, T[:3, 3].copy(), np.array([std, std, 2 * std]), T[:3, :3].copy(), rot_std,
                    key="anchors[8]"),
             Anchor(unseen_position, P[:3, 3].copy(), np.full(3, std), key="anchors[9]")]
    return AnchorSet(list(base.anchors) + extra, base.frame_id, base.source)


def test_a_surveyed_marker_never_seen_is_mapped_from_its_survey(ring, frames, truth, tmp_path):
    spread = set(_spread_ids(truth))
    full, position = [m for m in truth.ids if m not in spread][:2]
    seen = _without(_without(frames, full), position)
    anchors = _with_unseen(truth, full, position)
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors)
    for f in seen:
        b.add_frame(f)
    m = b.build()
    # The full-pose one: in the map at its surveyed pose with the survey's std, flagged; the other not.
    assert m.surveyed_only_ids == [full] and position not in m
    e = m[full]
    assert np.allclose(e.T_map_marker, truth.T_map_marker(full)) and e.observations == 0
    assert np.allclose(e.position_std, [0.002, 0.002, 0.004]) and np.allclose(e.rotation_std, 0.01)
    assert not any(x.surveyed_only for x in m if x.marker_id != full)
    points = {p["marker"]: p for p in m.anchors["points"]}
    assert points[full].get("surveyed_only") is True and "residual" not in points[full]
    assert points[position]["mapped"] is False
    s = b.summary()
    assert s["surveyed_only"] == [full] and s["surveyed_not_mapped"] == [position]
    assert f"surveyed but never detected, NOT mapped: [{position}]" in b.format_summary()
    # Saved and read back with its flag; the sanity checks pass (no residual to judge).
    path = tmp_path / "map.yaml"
    m.save(str(path))
    back = MarkerMap.load(str(path))
    assert back.surveyed_only_ids == [full] and np.allclose(back[full].position_std, e.position_std)
    # The option off: only detected markers.
    off = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors, options=MappingOptions(surveyed_unseen=False))
    for f in seen:
        off.add_frame(f)
    m_off = off.build()
    assert full not in m_off and m_off.surveyed_only_ids == []
    assert off.summary()["surveyed_not_mapped"] == [full, position]
    # A surveyed marker the recording does see is mapped from its detections, never flagged.
    both = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors)
    for f in frames:
        both.add_frame(f)
    assert both.build().surveyed_only_ids == [] and both.summary()["surveyed_only"] == []


def test_the_localizer_uses_a_surveyed_only_marker(ring, frames, truth):
    """A frame that sees only a marker placed from the survey localizes on it as on the true map
    (the survey is the marker's true pose here); without the marker the map has nothing to offer."""
    import dataclasses

    from aruco_ring_localization.localization import LocalizationParams, RingLocalizer

    spread = set(_spread_ids(truth))
    full, position = [m for m in truth.ids if m not in spread][:2]
    anchors = _with_unseen(truth, full, position, std=0.0005, rot_std=0.001)
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors)
    for f in _without(_without(frames, full), position):
        b.add_frame(f)
    m = b.build()
    only = [dataclasses.replace(f, cameras={c: dataclasses.replace(cf, observations=[o for o in cf.observations
                                                                                   if o.marker_id == full])
                                            for c, cf in f.cameras.items()}) for f in frames]
    only = [f for f in only if f.observation_count()]
    assert only, "no frame sees the marker"
    ours = RingLocalizer(ring, m, LocalizationParams(fusion="joint"))
    true = RingLocalizer(ring, truth, LocalizationParams(fusion="joint"))
    d = []
    for f in only:
        a, t = ours.process(f), true.process(f)
        assert a.ok == t.ok
        if a.ok:
            d.append(float(np.linalg.norm(a.T_map_base[:3, 3] - t.T_map_base[:3, 3])))
    assert d and max(d) < 1e-3, f"pose differences (m) {d}"
    without = MapBuilder(ring, MarkerSizes(0.2), anchors=anchors, options=MappingOptions(surveyed_unseen=False))
    for f in _without(_without(frames, full), position):
        without.add_frame(f)
    assert not RingLocalizer(ring, without.build(), LocalizationParams(fusion="joint")).process(only[0]).ok
