"""Ring frame assembly with ``slop: auto`` over a matrix of camera timings.

Synchronized cameras; free-running ones with evenly spaced phases (k * period / 8) and random
phases; stamp jitter 0-5 ms (1 sigma); a camera dropping frames; a dead camera; the ring's rate
changing 10 -> 5 -> 15 -> 10 Hz; a time jump back (a bag loop) and forward. Messages arrive in
the order of their stamp plus a random 5-15 ms transport delay.

What must hold in every case: every camera message lands in exactly one ring frame (except, at a
time jump back, the few of the pending frames that the reset discards), each camera at most once
per ring frame, and no ring frame is wider than one frame period. Where the timing allows it (the
cameras' largest phase gap at least 6 jitters) the ring frames are whole: after the first period
(before the period is measured) at most a few split frames.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import pytest

from aruco_ring_localization.detections import CameraFrame, RingFrameAssembler, parse_slop

CAMS = [f"cam{k}" for k in range(8)]
T0 = 100.0

#: (arrival, camera, stamp, message id, true period)
Event = Tuple[float, str, float, int, float]


def _stream(seed: int, phases: Sequence[float], jitter: float, segments: Sequence[Tuple[float, float]],
            drop: Optional[Dict[str, float]] = None, dead: Optional[Tuple[str, float]] = None,
            jump: Optional[Tuple[float, float]] = None) -> List[Event]:
    """Camera messages of ``segments`` ((duration s, rate Hz), ...); phases in periods."""
    rng = np.random.default_rng(seed)
    events, t, mid = [], T0, 0
    for duration, rate in segments:
        period = 1.0 / rate
        n = int(round(duration * rate))
        for k in range(n):
            for i, cam in enumerate(CAMS):
                s = t + (k + phases[i]) * period + (rng.normal(0.0, jitter) if jitter > 0 else 0.0)
                lost = drop is not None and cam in drop and rng.random() < drop[cam]
                if lost or (dead is not None and cam == dead[0] and s >= dead[1]):
                    continue
                stamp = s + jump[1] if jump is not None and s >= jump[0] else s
                events.append((s + 0.005 + rng.uniform(0.0, 0.01), cam, stamp, mid, period))
                mid += 1
        t += n * period
    events.sort()
    return events


def _assemble(events: List[Event], slop="auto"):
    a = RingFrameAssembler(CAMS, slop=slop, timeout=0.25)
    out, ids, periods = [], {}, {}
    for arrival, cam, stamp, mid, period in events:
        frame = CameraFrame(cam, stamp, [])
        ids[id(frame)], periods[id(frame)] = mid, period
        out += a.add(frame, arrival)
        out += a.poll(arrival)
    out += a.poll(np.inf)
    return a, out, ids, periods


def _check(events: List[Event], slop="auto", lost_at_jump: int = 0):
    """Assert the invariants; return (assembler, ring frames, fraction of whole frames)."""
    a, out, ids, periods = _assemble(events, slop)
    landed = [ids[id(f)] for rf in out for f in rf.cameras.values()]
    assert len(landed) == len(set(landed)), "a camera message landed in two ring frames"
    missing = len(events) - len(landed)
    assert 0 <= missing <= lost_at_jump, \
        f"{missing} of {len(events)} camera messages landed in no ring frame (late: {a.dropped_late})"
    steps = np.diff([rf.stamp for rf in out])
    # In stamp order, except where time jumped back (a bag loop), once per jump.
    assert np.all((steps > 0) | (steps < -1.0)) and np.sum(steps < 0) == a.time_jumps, \
        f"ring frames out of stamp order: {steps[steps <= 0]}"
    for rf in out:
        assert sorted(rf.cameras) + rf.missing and set(rf.cameras).isdisjoint(rf.missing)
        assert all(f.camera == c for c, f in rf.cameras.items())
        members = [f.stamp for f in rf.cameras.values()]
        period = max(periods[id(f)] for f in rf.cameras.values())  # members' period (of both, at a rate change)
        assert max(members) - min(members) < period, \
            f"ring frame at {rf.stamp:.3f} is {max(members) - min(members):.4f} s wide, period {period:.4f} s"
        assert rf.stamp == min(members)
    return a, out


def _whole(out, alive: int = 8, skip: float = 0.3) -> Tuple[int, int]:
    """(split frames, all frames) after the first ``skip`` s and before the stream's last 0.3 s."""
    end = max(rf.stamp for rf in out)
    body = [rf for rf in out if T0 + skip <= rf.stamp <= end - 0.3]
    return sum(len(rf.cameras) < alive for rf in body), len(body)


SYNC = np.zeros(8)
EVEN = np.arange(8) / 8.0
RANDOM = np.random.default_rng(3).uniform(0.0, 1.0, 8)  # largest gap 28 ms at 10 Hz


@pytest.mark.parametrize("jitter", [0.0, 0.002, 0.005])
@pytest.mark.parametrize("name,phases", [("synchronized", SYNC), ("even", EVEN), ("random", RANDOM)])
def test_every_message_lands_once_in_a_frame_at_most_one_period_wide(name, phases, jitter):
    _, out = _check(_stream(1, phases, jitter, [(20.0, 10.0)]))
    split, total = _whole(out)
    gaps = np.diff(np.r_[np.sort(phases), np.sort(phases)[0] + 1.0]) * 0.1
    if name == "synchronized" or gaps.max() >= 6 * jitter:
        assert split <= 2, f"{name}, jitter {jitter * 1e3:.0f} ms: {split} of {total} ring frames split"
    else:
        # Evenly spaced phases 12.5 ms apart with 5 ms of jitter: neighbours swap places; frames
        # may split, but never more than a camera per frame.
        assert split < total / 2, f"{split} of {total} split"


def test_the_stock_fixed_slop_splits_free_running_frames_and_auto_does_not():
    events = _stream(2, RANDOM, 0.002, [(20.0, 10.0)])
    _, fixed = _check(events, slop=0.03)
    _, auto = _check(events)
    assert _whole(fixed)[0] > 0.5 * _whole(fixed)[1], "0.03 s should split free-running frames"
    assert _whole(auto)[0] <= 2, _whole(auto)


def test_a_slop_as_wide_as_the_period_no_longer_drops_a_cameras_next_frame():
    # The late rule used to be stamp <= last + slop: with slop >= the period a camera's next
    # frame was dropped. Now a camera's next frame opens a new ring frame.
    a, out = _check(_stream(4, RANDOM, 0.002, [(10.0, 10.0)]), slop=0.15)
    assert a.dropped_late == 0


def test_a_camera_dropping_frames():
    events = _stream(5, RANDOM, 0.002, [(20.0, 10.0)], drop={"cam3": 0.2})
    _, out = _check(events)
    body = [rf for rf in out if T0 + 0.3 <= rf.stamp <= T0 + 19.7]
    others_split = sum(any(c != "cam3" for c in rf.missing) for rf in body)
    assert others_split <= 2, f"{others_split} frames lost a camera other than the one dropping frames"
    assert 0.1 * len(body) < sum("cam3" in rf.missing for rf in body) < 0.3 * len(body)


def test_a_dead_camera():
    a, out = _check(_stream(6, RANDOM, 0.002, [(20.0, 10.0)], dead=("cam5", T0 + 5.0)))
    after = [rf for rf in out if T0 + 7.0 <= rf.stamp <= T0 + 19.7]
    assert all(rf.missing == ["cam5"] for rf in after), [rf.missing for rf in after if rf.missing != ["cam5"]][:5]
    assert a.timing()[0] == pytest.approx(0.1, abs=0.003)


@pytest.mark.parametrize("phases", [SYNC, RANDOM], ids=["synchronized", "random"])
def test_rate_changes(phases):
    segments = [(10.0, 10.0), (10.0, 5.0), (10.0, 15.0), (10.0, 10.0)]
    a, out = _check(_stream(7, phases, 0.002, segments))
    starts = np.cumsum([0.0] + [d for d, _ in segments]) + T0
    for (t0, t1), (_, rate) in zip(zip(starts[:-1], starts[1:]), segments):
        steady = [rf for rf in out if t0 + 1.0 <= rf.stamp <= t1 - 0.3]
        split = sum(len(rf.cameras) < 8 for rf in steady)
        assert split <= 2, f"{split} of {len(steady)} frames split at {rate} Hz"
    assert a.timing()[0] == pytest.approx(0.1, abs=0.003)


@pytest.mark.parametrize("offset", [-50.0, 30.0], ids=["back", "forward"])
def test_a_time_jump(offset):
    events = _stream(8, RANDOM, 0.002, [(20.0, 10.0)], jump=(T0 + 10.0, offset))
    a, out = _check(events, lost_at_jump=8 if offset < 0 else 0)
    assert a.time_jumps == (1 if offset < 0 else 0)
    after = [rf for rf in out if T0 + 10.5 + offset <= rf.stamp <= T0 + 19.7 + offset]
    assert len(after) > 80 and sum(len(rf.cameras) < 8 for rf in after) <= 2


def test_synchronized_frames_keep_their_timeout_and_free_running_ones_wait_for_their_spread():
    # A camera misses one frame: synchronized, the frame goes out input/timeout after its first
    # member as before; free-running, after the first member plus the phases still to come.
    for phases, extra in ((SYNC, 0.0), (RANDOM, 0.1 * (1 - 0.0284 / 0.1))):
        a = RingFrameAssembler(CAMS, timeout=0.25, silence=None)
        order = np.argsort(phases)
        out = []
        for k in range(21):  # frame 20 stays pending
            for i in order:
                s = T0 + (k + phases[i]) * 0.1
                if k == 20 and CAMS[i] == CAMS[order[-1]]:
                    continue  # the last camera of the frame misses frame 20
                out += a.add(CameraFrame(CAMS[i], s), s + 0.01)
        first = T0 + (20 + phases[order[0]]) * 0.1 + 0.01
        pending = [g for g in a._pending if abs(g.frame.stamp - (first - 0.01)) < 1e-6]
        assert len(pending) == 1
        assert pending[0].deadline - first == pytest.approx(0.25 + extra, abs=0.01)


def test_parse_slop():
    assert parse_slop("auto") is None and parse_slop(" AUTO ") is None
    assert parse_slop(0.09) == 0.09 and parse_slop("0.09") == 0.09 and parse_slop(0) == 0.0
    for bad in ("fast", -0.1, float("nan"), True, None):
        with pytest.raises(ValueError, match="slop"):
            parse_slop(bad)
