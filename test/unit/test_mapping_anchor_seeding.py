"""MapBuilder with anchors: groups of markers never seen together with the others are placed through
their own surveyed markers (anchored seeding), or reported with the reason; never dropped silently.

The simulated lab's 10 markers, split in two groups that no image links: stations 0-2 see only
group A, stations 3-4 only group B (the other group's detections are removed from their frames).
"""
from __future__ import annotations

import dataclasses
from typing import Dict, List

import numpy as np
import pytest

from aruco_ring_localization.anchors import Anchor, AnchorSet
from aruco_ring_localization.detections import CameraFrame, RingFrame
from aruco_ring_localization.evaluation.maps import map_error
from aruco_ring_localization.mapping import MapBuilder, MappingOptions
from aruco_ring_localization.marker_map import check_map
from aruco_ring_localization.markers import MarkerSizes
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Scene

GROUP_A = (42, 126, 203, 318, 580, 777)
GROUP_B = (17, 64, 95, 451)
STATIONS_A = (0, 1, 2)


def _keep(frame: RingFrame, ids) -> RingFrame:
    return RingFrame(frame.stamp, {c: CameraFrame(cf.camera, cf.stamp, [o for o in cf.observations
                                                                        if o.marker_id in ids], cf.model)
                                   for c, cf in frame.cameras.items()}, list(frame.missing))


@pytest.fixture(scope="module")
def frames(ring, scene) -> List[RingFrame]:
    sim = RingSimulator(scene, ring, pixel_noise=0.3, seed=4)
    out = []
    for k, p in enumerate(scene.mapping_stations):
        ids = GROUP_A if k in STATIONS_A else GROUP_B
        out += [_keep(sim.observe(Scene.T_world_base(p), stamp=10.0 * k + 0.1 * i), ids) for i in range(6)]
    return out


@pytest.fixture(scope="module")
def truth(scene):
    return scene.truth_map()


def _anchor(truth, m: int, pose: bool, std: float = 0.001, rot_std_deg: float = 0.05) -> Anchor:
    T = truth.T_map_marker(m)
    return Anchor(m, T[:3, 3].copy(), np.full(3, std), T[:3, :3].copy() if pose else None,
                  np.radians(rot_std_deg) if pose else None, "test survey", f"marker {m}")


def _build(ring, frames, anchors, options=None):
    b = MapBuilder(ring, MarkerSizes(0.2), options=options, anchors=anchors)
    for f in frames:
        b.add_frame(f)
    return b, b.build()


def _strict_mm(m, truth, ids) -> Dict[int, float]:
    return {i: 1000.0 * float(np.linalg.norm(m.T_map_marker(i)[:3, 3] - truth.T_map_marker(i)[:3, 3])) for i in ids}


def _sigmas(m, truth, ids) -> Dict[int, float]:
    """Largest per-axis error of each marker in units of the std the map reports for it."""
    std = {e.marker_id: e.position_std for e in m}
    return {i: float(np.max(np.abs(m.T_map_marker(i)[:3, 3] - truth.T_map_marker(i)[:3, 3]) / std[i])) for i in ids}


def test_the_split_leaves_two_groups_never_seen_together(ring, frames):
    b = MapBuilder(ring, MarkerSizes(0.2))
    for f in frames:
        b.add_frame(f)
    comps = b._components(b._groups())
    assert [sorted(c) for c in comps] == [sorted(GROUP_A), sorted(GROUP_B)]


def test_a_group_with_one_surveyed_pose_is_placed_through_it(ring, frames, truth):
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580)] + [_anchor(truth, 64, pose=True)],
                       source="survey.yaml")
    b, m = _build(ring, frames, survey)
    assert sorted(m.ids) == sorted(GROUP_A + GROUP_B), b.format_summary()
    assert b.summary()["anchor_seeded_groups"] == 1 and b.summary()["unlinked"] == []
    err = _strict_mm(m, truth, GROUP_B)
    # Strict convention (nothing fitted). The group rests on one 0.2 m marker: its surveyed pose and
    # the stations' view of it, whose orientation the images fix only to about a degree (a few cm
    # across the group); the map says so in each marker's std, and the errors stay within it.
    assert err[64] < 1.0 and max(err.values()) < 100.0, f"group B strict errors {err} mm"
    sig = _sigmas(m, truth, GROUP_B)
    assert max(sig.values()) < 4.0, f"group B errors in sigmas {sig}"
    assert check_map(m) == []


def test_the_paper_map_places_the_group_too(ring, frames, truth):
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580)] + [_anchor(truth, 64, pose=True)],
                       source="survey.yaml")
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=survey)
    for f in frames:
        b.add_frame(f)
    m = b.build("paper")
    assert sorted(m.ids) == sorted(GROUP_A + GROUP_B)
    err = _strict_mm(m, truth, GROUP_B)
    assert max(err.values()) < 150.0, f"group B strict errors {err} mm (initialisation only)"


def test_without_a_surveyed_marker_the_group_is_reported_not_mapped(ring, frames, truth):
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580)], source="survey.yaml")
    b, m = _build(ring, frames, survey)
    assert sorted(m.ids) == sorted(GROUP_A)
    why = b.unmapped(m)
    assert sorted(why) == sorted(GROUP_B)
    assert all("holds no surveyed marker" in w and "survey.yaml" in w for w in why.values()), why
    assert "NOT in the map" in b.format_unmapped(m)


def test_one_surveyed_position_cannot_place_a_group_and_says_so(ring, frames, truth):
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580, 64)], source="survey.yaml")
    b, m = _build(ring, frames, survey)
    assert not set(GROUP_B) & set(m.ids)
    why = b.unmapped(m)[95]
    assert "[64]" in why and "no single view" in why, why


def test_two_surveyed_positions_place_a_ground_robots_group_level(ring, frames, truth):
    """Planar stations (a ground robot): 2 surveyed positions seen from one station fix its pose (the
    floor gives the tilt); the seeded station is held level in the adjustment."""
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580, 17, 95)], source="survey.yaml")
    b, m = _build(ring, frames, survey)
    assert sorted(m.ids) == sorted(GROUP_A + GROUP_B), b.format_summary()
    init = b._initialize()
    assert set(init.seeds.values()) == {"points_level"}
    err = _strict_mm(m, truth, GROUP_B)
    assert max(err[17], err[95]) < 1.0 and max(err.values()) < 50.0, f"group B strict errors {err} mm"
    sig = _sigmas(m, truth, GROUP_B)
    assert max(sig.values()) < 4.0, f"group B errors in sigmas {sig}"


def test_two_surveyed_positions_do_not_place_a_6dof_rigs_group(ring, frames, truth):
    """Without the planar prior a station's tilt about the line of 2 points is free: not seeded."""
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580, 17, 95)], source="survey.yaml")
    b, m = _build(ring, frames, survey, MappingOptions(planar=False))
    assert not set(GROUP_B) & set(m.ids)
    assert "no single view" in b.unmapped(m)[64]


def test_the_main_group_is_the_largest_one_whose_survey_fixes_a_frame(ring, frames, truth):
    """Group B is the only one surveyed (a pose): the map grows from it and A, unsurveyed, is reported."""
    b, m = _build(ring, frames, AnchorSet([_anchor(truth, 64, pose=True)], source="survey.yaml"))
    assert sorted(m.ids) == sorted(GROUP_B)
    assert b.summary()["anchor_seeded_groups"] == 0
    assert all("holds no surveyed marker" in w for w in b.unmapped(m).values())


def test_a_mirrored_view_of_the_surveyed_marker_does_not_seed(ring, frames, truth):
    """The seed uses a surveyed orientation only through an unambiguous view: with every view of the
    surveyed marker ambiguous (max_ambiguity 0), its pose cannot seed the group."""
    survey = AnchorSet([_anchor(truth, m, pose=False) for m in (42, 126, 580)] + [_anchor(truth, 64, pose=True)],
                       source="survey.yaml")
    b = MapBuilder(ring, MarkerSizes(0.2), anchors=survey)
    for f in frames:
        b.add_frame(f)
    b._unambiguous = lambda g: g.marker_id != 64          # type: ignore[assignment]
    b._init_cache = None
    init = b._initialize()
    assert not set(GROUP_B) & set(init.T_W_markers)
    assert init.unplaced and all("[64]" in w for w in init.unplaced.values())
