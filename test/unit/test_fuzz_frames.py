"""Fuzzing of the runtime data path of the core: detections and ring frame assembly.

* :func:`sanitize_observations` on arbitrary corner arrays (NaN, inf, huge, wrong shapes,
  duplicate ids): never raises; what it keeps is finite, (4, 2), convex, unique per id and not
  ignored; every input is either kept or counted in exactly one reason.
* :class:`RingFrameAssembler` under random streams (cameras out of order, silent cameras, stamps
  jumping back, duplicates, unknown cameras, a clock that stalls): never raises; every emitted
  ring frame has each camera at most once, ``missing`` is exactly the complement, no camera frame
  is emitted twice, pending groups stay bounded; after a quiet period every group has gone out.
"""
from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from aruco_ring_localization.detections import (CameraFrame, MarkerObservation, RingFrameAssembler,
                                            sanitize_observations)
from aruco_ring_localization.markers import quad_is_degenerate

from fuzz_support import FUZZ

CAMS = [f"cam{k}" for k in range(8)]

coord = st.floats(allow_nan=True, allow_infinity=True) | st.floats(-3000, 3000)
good_quad = st.builds(lambda x, y, s, a: np.array([[x, y], [x + s, y], [x + s, y + s * a], [x, y + s * a]]),
                      st.floats(0, 1200), st.floats(0, 900), st.floats(-200, 200), st.floats(0.2, 3))


def corner_arrays():
    shapes = st.sampled_from([(4, 2), (4, 2), (4, 2), (3, 2), (4, 3), (8,), (0,), (4, 2, 1), (5, 2)])
    return good_quad | shapes.flatmap(lambda s: st.lists(coord, min_size=int(np.prod(s)), max_size=int(np.prod(s)))
                                      .map(lambda v, s=s: np.array(v, dtype=float).reshape(s)))


observations = st.lists(st.builds(MarkerObservation, st.integers(0, 12), corner_arrays()), max_size=12)


@FUZZ
@given(observations, st.frozensets(st.integers(0, 12), max_size=3),
       st.sampled_from([(None, None), (1280, 960), (0, 0), (1, 1)]))
def test_fuzz_sanitize_observations(obs, ignore, size):
    kept, reasons = sanitize_observations(obs, ignore=ignore, width=size[0], height=size[1])
    assert len(kept) + sum(reasons.values()) == len(obs), (len(kept), reasons, len(obs))
    ids = [o.marker_id for o in kept]
    assert len(ids) == len(set(ids)), f"duplicate ids kept: {ids}"
    for o in kept:
        c = np.asarray(o.corners)
        assert c.shape == (4, 2) and np.all(np.isfinite(c)), c
        assert o.marker_id not in ignore
        assert not quad_is_degenerate(c)


def _ops():
    """One stream event: (camera index or 8 = unknown, stamp step, clock step, markers)."""
    return st.tuples(st.integers(0, 8), st.sampled_from([0.0, 0.0, 0.001, 0.02, 0.1, 0.5, -0.05, -2.0, 5.0]),
                     st.sampled_from([0.0, 0.01, 0.05, 0.1, 0.3]), st.integers(0, 2))


@FUZZ
@given(st.lists(_ops(), max_size=120), st.sampled_from([0.0, 0.01, 0.03, "auto"]), st.sampled_from([0.05, 0.25]),
       st.sampled_from([1, 3, 8]), st.sets(st.integers(0, 7), max_size=8))
def test_fuzz_ring_frame_assembler(events, slop, timeout, max_pending, silent):
    asm = RingFrameAssembler(CAMS, slop=slop, timeout=timeout, max_pending=max_pending)
    stamp, now = 100.0, 0.0
    sent = 0
    emitted = []
    for cam, dstamp, dnow, nmark in events:
        stamp += dstamp
        now += dnow
        name = CAMS[cam] if cam < 8 else "not_a_camera"
        if cam in silent:
            emitted += asm.poll(now)
            continue
        frame = CameraFrame(name, stamp, [MarkerObservation(i, np.zeros((4, 2))) for i in range(nmark)])
        sent += cam < 8
        emitted += asm.add(frame, now)
        assert len(asm._pending) <= max_pending, len(asm._pending)
    emitted += asm.poll(now + 10 * timeout + 1.0)
    assert not asm._pending, "groups still pending after a quiet period longer than the timeout"
    seen_ids = set()
    for rf in emitted:
        assert set(rf.cameras) | set(rf.missing) == set(CAMS), (rf.cameras.keys(), rf.missing)
        assert not set(rf.cameras) & set(rf.missing)
        assert rf.cameras, "an empty ring frame was emitted"
        for name, cf in rf.cameras.items():
            assert cf.camera == name
            assert id(cf) not in seen_ids, "a camera frame was emitted twice"
            seen_ids.add(id(cf))
            if slop != "auto":
                assert 0 <= cf.stamp - rf.stamp <= slop + 1e-9, (cf.stamp, rf.stamp, slop)
    # Every camera frame either went out or was counted as late (or went stale with a time jump).
    assert len(seen_ids) + asm.dropped_late <= sent
    assert all(s not in {CAMS[k] for k in silent} for rf in emitted for s in rf.cameras)


@FUZZ
@given(st.lists(st.tuples(st.integers(0, 7), st.floats(allow_nan=True, allow_infinity=True)), max_size=30),
       st.sampled_from([0.02, "auto"]))
def test_fuzz_ring_frame_assembler_bad_stamps(events, slop):
    """NaN or infinite stamps (a corrupted header) must not wedge the assembler or raise."""
    asm = RingFrameAssembler(CAMS, slop=slop, timeout=0.1)
    now = 0.0
    for cam, stamp in events:
        now += 0.05
        asm.add(CameraFrame(CAMS[cam], stamp), now)
    asm.poll(now + 5.0)
    # Afterwards normal frames still go through.
    out = []
    for k in range(8):
        out += asm.add(CameraFrame(CAMS[k], 1e12), now + 6.0)
    assert out and set(out[-1].cameras) == set(CAMS), [sorted(f.cameras) for f in out]
