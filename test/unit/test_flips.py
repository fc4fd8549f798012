"""No pose flips: the lab cases of bench/flip_cases.py, on the pinhole ring and on a seeded fisheye
(equidistant) ring, through the whole localization pipeline (localizer, gate, filter).

Every case flipped before the calibration-aware estimator and the flip-aware gate (measured on
main 8d5b1c8 with the same cases, 3 seeds: far face-on marker 99-140 flipped filtered frames of 180,
two cameras with one marker each up to 24 of 60 on the fisheye ring, the wrong prediction after a
kidnap 78-90 flipped measurements accepted of 90 on the fisheye ring). The tests require none."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from aruco_ring_localization.localization import LocalizationParams, RingLocalizer
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap
from aruco_ring_localization.ring import CameraRing

from helpers import REPO, RING_YAML

sys.path.insert(0, str(REPO / "bench"))
import flip_cases  # noqa: E402

CASES = {c.name: c for c in flip_cases.cases()}


@pytest.fixture(scope="module")
def rings():
    ring = CameraRing.load(str(RING_YAML))
    return {"pinhole": ring, "fisheye": flip_cases.fisheye_ring(ring, seed=3)}


@pytest.mark.parametrize("ring_kind", ["pinhole", "fisheye"])
@pytest.mark.parametrize("name", sorted(CASES))
def test_no_flip_reaches_the_filter(rings, ring_kind, name):
    case = CASES[name]
    for seed in range(2):
        s = flip_cases.run_case(case, rings[ring_kind], LocalizationParams(fusion="joint"), seed=seed)
        assert s["accepted_flips"] == 0, f"{name} ({ring_kind}, seed {seed}): flipped measurements accepted: {s}"
        assert s["filtered_flips"] == 0, f"{name} ({ring_kind}, seed {seed}): filtered output flipped: {s}"
        assert s["step_excess"] <= 1e-9, f"{name}: the output moved more than the gate allowed: {s}"
        if name.startswith("two_cameras"):
            # The joint estimate resolves them: a pose every frame, none of them ambiguous.
            assert s["outputs"] == s["frames"] and s["ambiguous"] == 0, f"{name} ({ring_kind}): {s}"
        if case.wrong_start:
            # The clear image wins over the wrong prediction: re-initialised after recovery_count frames.
            assert 0 <= s["recovered_at"] <= 5, f"{name} ({ring_kind}): no recovery from the wrong pose: {s}"
        if name.startswith("far_face_on"):
            # Every measurement is marked ambiguous (and kept out of the filter): the two IPPE
            # poses of a far face-on marker are both decimetres off.
            assert s["ambiguous"] == s["frames"], f"{name} ({ring_kind}): {s}"


def test_both_ippe_poses_are_carried_into_the_joint_problem(rings):
    """Two cameras each seeing one marker, with a prediction on the wrong IPPE combination: the
    joint estimate still lands on the truth (the prediction is one start among all IPPE poses)."""
    case = CASES["two_cameras_c"]
    ring = rings["pinhole"]  # (the fisheye ring sees each marker with several cameras)
    mm = MarkerMap([MarkerEntry(i, T, flip_cases.SIZE) for i, T in case.markers.items()])
    loc = RingLocalizer(ring, mm, LocalizationParams(fusion="joint"))
    rng = np.random.default_rng(5)
    frame = flip_cases.observe(ring, case.markers, case.truth[0], 0.1, rng, case.noise)
    views = loc._gather(frame, {})
    assert len(views) == 2 and all(len(v.ids) == 1 for v in views.values()), "not two single-marker cameras"
    # The worst prediction available: the pose of the single-marker IPPE alternative farthest away.
    alts = [a for v in views.values() for a in loc._camera_estimate(v, None)[1]]
    wrong = max(alts, key=lambda A: np.linalg.norm(A[:2, 3] - case.truth[0][:2, 3]))
    assert np.linalg.norm(wrong[:2, 3]) > 0.5, "no far IPPE alternative: the case proves nothing"
    res = loc.process(frame, prediction=wrong)
    assert res.ok and res.method == "joint" and not res.ambiguous, f"{res.method}, ambiguous {res.ambiguous}"
    assert np.linalg.norm(res.T_map_base[:2, 3] - case.truth[0][:2, 3]) < 0.2, res.se2
