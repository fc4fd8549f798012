"""Unit tests of frames.py: ring frame assembly by stamp (timeouts, dead cameras, clock jumps, late
frames) and sanitising of detections."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization.detections import (CameraFrame, MarkerObservation, RingFrame, RingFrameAssembler,
                                            sanitize_observations)

CAMS = [f"cam{k}" for k in range(8)]
SQUARE = np.array([[100.0, 100.0], [140.0, 100.0], [140.0, 140.0], [100.0, 140.0]])


def _frame(cam: str, stamp: float, n_obs: int = 0) -> CameraFrame:
    return CameraFrame(cam, stamp, [MarkerObservation(i, SQUARE + 50 * i) for i in range(n_obs)])


def _assembler(**kw) -> RingFrameAssembler:
    args = dict(slop=0.03, timeout=0.25)
    args.update(kw)
    return RingFrameAssembler(CAMS, **args)


def test_complete_group_goes_out_with_the_last_camera():
    a = _assembler()
    rng = np.random.default_rng(40)
    jitter = rng.uniform(-0.01, 0.01, size=8)
    out = []
    for k, cam in enumerate(CAMS):
        assert out == [], f"emitted before all cameras reported (after {cam})"
        out = a.add(_frame(cam, 5.0 + jitter[k], n_obs=k % 3), now=5.02 + 0.001 * k)
    assert len(out) == 1
    rf = out[0]
    assert isinstance(rf, RingFrame) and sorted(rf.cameras) == CAMS and rf.missing == []
    assert rf.stamp == pytest.approx(5.0 + jitter.min())
    assert rf.observation_count() == sum(k % 3 for k in range(8))
    assert a.poll(now=100.0) == []


def test_frames_are_grouped_by_stamp_within_slop():
    a = _assembler()
    # Two captures 0.1 s apart, interleaved arrivals.
    emitted = []
    for k, cam in enumerate(CAMS):
        emitted += a.add(_frame(cam, 1.0 + 0.002 * k), now=1.05)
        emitted += a.add(_frame(cam, 1.1 + 0.002 * k), now=1.06)
    assert [rf.stamp for rf in emitted] == [pytest.approx(1.0), pytest.approx(1.1)]
    for rf, base in zip(emitted, (1.0, 1.1)):
        assert sorted(rf.cameras) == CAMS
        assert all(abs(f.stamp - base) < 0.03 for f in rf.cameras.values())


def test_incomplete_group_goes_out_after_timeout_listing_missing_cameras():
    a = _assembler()
    for cam in CAMS[:6]:
        assert a.add(_frame(cam, 2.0), now=2.01) == []
    assert a.poll(now=2.01 + 0.2) == []
    out = a.poll(now=2.01 + 0.25)
    assert len(out) == 1
    assert sorted(out[0].cameras) == CAMS[:6] and out[0].missing == ["cam6", "cam7"]
    assert a.poll(now=3.0) == []


def test_timeout_is_counted_from_the_first_member():
    a = _assembler()
    a.add(_frame("cam0", 2.0), now=2.0)
    a.add(_frame("cam1", 2.0), now=2.2)
    out = a.poll(now=2.26)
    assert len(out) == 1 and sorted(out[0].cameras) == ["cam0", "cam1"]


def test_a_dead_camera_never_stalls_the_others():
    a = _assembler()
    rate, n = 10.0, 100
    emitted = []
    for i in range(n):
        stamp = 100.0 + i / rate
        for k, cam in enumerate(CAMS[:7]):  # cam7 is dead
            now = stamp + 0.02 + 0.001 * k  # transport delay
            emitted += [(now, rf) for rf in a.add(_frame(cam, stamp), now)]
        emitted += [(stamp + 0.05, rf) for rf in a.poll(stamp + 0.05)]
    assert len(emitted) >= n - 3, f"only {len(emitted)} of {n} ring frames came out"
    stamps = [rf.stamp for _, rf in emitted]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    for now, rf in emitted:
        assert rf.missing == ["cam7"] and len(rf.cameras) == 7
        latency = now - rf.stamp
        assert latency <= 0.02 + 0.25 + 1 / rate + 1e-9, f"ring frame {rf.stamp} came out {latency:.3f} s late"
    assert a.silent_cameras(now=110.0, silence=1.0) == ["cam7"]
    assert a.dropped_late == 0 and a.time_jumps == 0


def test_silent_cameras():
    a = _assembler()
    assert a.silent_cameras(now=0.0, silence=1.0) == CAMS
    a.add(_frame("cam3", 1.0), now=1.0)
    assert a.silent_cameras(now=1.5, silence=1.0) == [c for c in CAMS if c != "cam3"]
    assert "cam3" in a.silent_cameras(now=2.5, silence=1.0)


def test_time_jump_backwards_resets():
    a = _assembler()
    for cam in CAMS:
        a.add(_frame(cam, 50.0), now=50.0)
    a.add(_frame("cam0", 50.1), now=50.1)  # pending group at the old time
    # A bag loops: stamps restart at 10 s.
    out = []
    for cam in CAMS:
        out += a.add(_frame(cam, 10.0), now=50.2)
    assert a.time_jumps == 1
    assert len(out) == 1 and out[0].stamp == 10.0 and sorted(out[0].cameras) == CAMS
    # The stale pending group of 50.1 s was discarded, not emitted later.
    assert a.poll(now=60.0) == []
    out = []
    for cam in CAMS:
        out += a.add(_frame(cam, 10.1), now=50.3)
    assert len(out) == 1 and a.dropped_late == 0


def test_late_frame_of_an_emitted_group_is_dropped():
    a = _assembler()
    for cam in CAMS[:7]:
        a.add(_frame(cam, 10.0), now=10.01)
    out = a.poll(now=10.3)
    assert len(out) == 1 and out[0].missing == ["cam7"]
    # cam7's frame of the same capture arrives after the group went out: it is late.
    assert a.add(_frame("cam7", 10.0), now=10.31) == []
    assert a.add(_frame("cam7", 10.02), now=10.32) == []
    assert a.add(_frame("cam6", 9.5), now=10.33) == []
    assert a.poll(now=20.0) == [], "a late frame came out as a ring frame of its own"
    assert a.dropped_late == 3 and a.time_jumps == 0
    # The next capture is assembled normally.
    out = []
    for cam in CAMS:
        out += a.add(_frame(cam, 10.1), now=10.4)
    assert len(out) == 1 and out[0].missing == []


def test_complete_newer_group_flushes_older_incomplete_ones():
    a = _assembler()
    a.add(_frame("cam0", 3.0), now=3.0)
    out = []
    for cam in CAMS:
        out += a.add(_frame(cam, 3.1), now=3.1)
    assert [rf.stamp for rf in out] == [3.0, 3.1]
    assert out[0].missing == CAMS[1:] and out[1].missing == []


def test_max_pending_bounds_memory():
    a = _assembler(timeout=100.0, max_pending=4)
    out = []
    for i in range(10):
        out += a.add(_frame("cam0", float(i)), now=0.0)
    assert len(a._pending) <= 4
    assert [rf.stamp for rf in out] == [float(i) for i in range(6)]


def test_unknown_camera_is_ignored_and_bad_arguments_raise():
    a = _assembler()
    assert a.add(_frame("cam99", 1.0), now=1.0) == []
    assert a.poll(now=10.0) == []
    with pytest.raises(ValueError):
        RingFrameAssembler([])
    with pytest.raises(ValueError):
        RingFrameAssembler(CAMS, slop=-1.0)
    with pytest.raises(ValueError):
        RingFrameAssembler(CAMS, timeout=0.0)


def test_single_camera_ring_emits_every_frame():
    a = RingFrameAssembler(["cam0"], slop=0.01, timeout=0.5)
    for i in range(5):
        out = a.add(_frame("cam0", i * 0.1), now=i * 0.1)
        assert len(out) == 1 and out[0].stamp == pytest.approx(i * 0.1)


# --- sanitize_observations ---------------------------------------------------------------------------

def test_sanitize_keeps_good_detections_untouched():
    obs = [MarkerObservation(i, SQUARE + 60 * i) for i in range(4)]
    kept, reasons = sanitize_observations(obs, width=1280, height=960)
    assert [o.marker_id for o in kept] == [0, 1, 2, 3] and reasons == {}
    assert all(k is o for k, o in zip(kept, obs))


def test_sanitize_drops_and_counts_each_reason():
    bowtie = SQUARE[[0, 2, 1, 3]]
    obs = [
        MarkerObservation(1, SQUARE),                                        # kept
        MarkerObservation(2, np.where(np.eye(4, 2, dtype=bool), np.nan, SQUARE)),  # NaN
        MarkerObservation(3, SQUARE[:3]),                                    # wrong shape
        MarkerObservation(4, bowtie),                                        # degenerate
        MarkerObservation(5, SQUARE * 0.01),                                 # tiny
        MarkerObservation(6, SQUARE + 10.0),                                 # duplicate id ...
        MarkerObservation(6, SQUARE + 300.0),                                # ... both dropped
        MarkerObservation(7, SQUARE + 20.0),                                 # ignored
        MarkerObservation(8, SQUARE + 1e5),                                  # far outside the image
        MarkerObservation(9, SQUARE.tolist()),                               # list corners: converted
    ]
    kept, reasons = sanitize_observations(obs, ignore={7, 100}, width=1280, height=960)
    assert [o.marker_id for o in kept] == [1, 9]
    assert isinstance(kept[1].corners, np.ndarray) and kept[1].corners.shape == (4, 2)
    assert reasons == {"non-finite": 2, "degenerate": 2, "duplicate id": 2, "ignored": 1, "outside image": 1}, reasons


def test_sanitize_duplicate_counts_only_usable_copies():
    obs = [MarkerObservation(5, SQUARE), MarkerObservation(5, np.full((4, 2), np.nan))]
    kept, reasons = sanitize_observations(obs)
    assert [o.marker_id for o in kept] == [5] and reasons == {"non-finite": 1}


def test_sanitize_without_image_size_keeps_far_corners():
    kept, reasons = sanitize_observations([MarkerObservation(1, SQUARE + 1e5)])
    assert len(kept) == 1 and reasons == {}


def test_sanitize_empty():
    assert sanitize_observations([]) == ([], {})


@pytest.mark.parametrize("size", [(1280, 960), (None, None)])
def test_sanitize_scalar_and_array_paths_agree(monkeypatch, size):
    # Up to detections.SCALAR_SANITIZE detections are checked on Python floats, more with numpy:
    # the same kept detections (the same objects) and the same counts for every kind of input,
    # hostile ones included (NaN, inf, 1e200, zero, self-crossing, far outside, duplicates, ints).
    import warnings

    from aruco_ring_localization import detections

    rng = np.random.default_rng(11)
    kinds = [lambda c: c, lambda c: c * 1e200, lambda c: np.where(rng.random((4, 2)) < 0.3, np.nan, c),
             lambda c: np.where(rng.random((4, 2)) < 0.3, -np.inf, c), lambda c: c * 0.02, lambda c: c[[0, 2, 1, 3]],
             lambda c: c + rng.choice([-1, 1]) * rng.uniform(1000, 3000), lambda c: np.zeros((4, 2)),
             lambda c: np.rint(c).astype(np.int64), lambda c: c.tolist()]
    cases = []
    for _ in range(400):
        n = int(rng.integers(1, detections.SCALAR_SANITIZE + 1))
        obs = []
        for _ in range(n):
            c = rng.normal(0, 15, (4, 2)) + rng.uniform(0, 1200, (1, 2))
            c = c[[0, 3, 2, 1]] if rng.random() < 0.5 else c   # either orientation
            obs.append(MarkerObservation(int(rng.integers(-1, 12)), kinds[int(rng.integers(len(kinds)))](c)))
        cases.append(obs)
    width, height = size
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # neither path may warn about overflow or NaN
        scalar = [sanitize_observations(obs, ignore={3}, width=width, height=height) for obs in cases]
        monkeypatch.setattr(detections, "SCALAR_SANITIZE", 0)
        array = [sanitize_observations(obs, ignore={3}, width=width, height=height) for obs in cases]
    kept_total = 0
    for (k_s, r_s), (k_a, r_a) in zip(scalar, array):
        assert r_s == r_a
        assert [o.marker_id for o in k_s] == [o.marker_id for o in k_a]
        for a, b in zip(k_s, k_a):
            assert a.corners.dtype == b.corners.dtype == np.float64
            np.testing.assert_array_equal(a.corners, b.corners)
        kept_total += len(k_s)
    reasons = set().union(*(r for _, r in scalar))
    expected = {"ignored", "negative id", "non-finite", "degenerate", "duplicate id"}
    expected |= {"outside image"} if width else set()
    assert kept_total > 100 and reasons == expected, reasons


def _run_10hz(a: RingFrameAssembler, cams, t0: float, n: int):
    """Feed ``n`` frames at 10 Hz from ``cams`` (arrival = stamp + 20 ms); return (latencies, frames)."""
    latencies, frames = [], []
    for i in range(n):
        t = t0 + 0.1 * i
        for k, cam in enumerate(cams):
            for rf in a.add(_frame(cam, t), now=t + 0.02 + 0.001 * k):
                latencies.append(t + 0.02 + 0.001 * k - rf.stamp)
                frames.append(rf)
        for rf in a.poll(now=t + 0.099):
            latencies.append(t + 0.099 - rf.stamp)
            frames.append(rf)
    return np.array(latencies), frames


def test_a_dead_camera_stops_delaying_frames_once_it_is_silent():
    a = _assembler(timeout=0.25, silence=1.0)
    _run_10hz(a, CAMS, 0.0, 10)              # all 8 cameras for 1 s
    lat, frames = _run_10hz(a, CAMS[:7], 1.0, 30)   # cam7 dies at t = 1 s
    late = lat[frames.index(next(f for f in frames if f.stamp >= 2.5)):]
    assert np.all(late < 0.05), f"frames still wait for the dead camera: latency up to {late.max():.3f} s"
    assert all(f.missing == ["cam7"] for f in frames), [f.missing for f in frames if f.missing != ["cam7"]]
    # While it was not yet known silent, the frames waited (up to the timeout), they were not cut short.
    assert lat[:5].max() > 0.09, f"latency right after the death {lat[:5]}"


def test_without_silence_every_frame_waits_for_the_dead_camera():
    a = _assembler(timeout=0.25, silence=None)
    _run_10hz(a, CAMS, 0.0, 10)
    lat, frames = _run_10hz(a, CAMS[:7], 1.0, 30)
    assert np.median(lat) > 0.09, f"median latency {np.median(lat):.3f} s"


def test_after_a_blackout_the_first_frame_waits_for_every_camera():
    a = _assembler(timeout=0.25, silence=1.0)
    _run_10hz(a, CAMS, 0.0, 10)
    a.poll(now=10.0)
    _, frames = _run_10hz(a, CAMS, 20.0, 3)  # all cameras back after 19 s of silence
    assert frames and all(sorted(f.cameras) == CAMS for f in frames), [sorted(f.cameras) for f in frames]


def test_why_a_frame_went_out_incomplete_is_counted():
    # timeout: six cameras, then the timeout
    a = _assembler(silence=None)
    for cam in CAMS[:6]:
        a.add(_frame(cam, 2.0), now=2.0)
    a.poll(now=2.3)
    assert a.incomplete == {"timeout": 1, "silent": 0, "overtaken": 0}
    # overtaken: cam7 lost the frame at 3.0; the frame at 3.1 completes first and pushes it out
    for cam in CAMS[:7]:
        a.add(_frame(cam, 3.0), now=3.0)
    out = []
    for cam in CAMS:
        out += a.add(_frame(cam, 3.1), now=3.05)
    assert [rf.missing for rf in out] == [["cam7"], []]
    assert a.incomplete == {"timeout": 1, "silent": 0, "overtaken": 1}


def test_a_lagging_camera_catches_up_within_the_timeout():
    # One camera's callback 1.5 s (15 frames at 10 Hz) behind the others, within a 5 s timeout:
    # with a fixed 8 pending frames the oldest went out without it; now every frame is whole.
    a = _assembler(timeout=5.0, silence=None)
    stamps = [10.0 + 0.1 * k for k in range(30)]
    out = []
    for k, t in enumerate(stamps):
        for cam in CAMS[:7]:
            out += a.add(_frame(cam, t), now=t)
        if k >= 15:
            out += a.add(_frame("cam7", stamps[k - 15]), now=t)
    for t in stamps[15:]:
        out += a.add(_frame("cam7", t), now=stamps[-1] + 0.01)
    assert len(out) == 30 and all(rf.missing == [] for rf in out), [rf.missing for rf in out if rf.missing][:3]
    assert a.max_pending >= 50 * 5.0


def test_simultaneous_parts_group_cameras_exposed_together():
    from aruco_ring_localization.detections import CameraFrame, RingFrame, simultaneous_parts
    f = RingFrame(stamp=1.0, missing=["cam7"])
    for name, t in [("cam2", 1.050), ("cam0", 1.000), ("cam1", 1.004), ("cam3", 1.051), ("cam4", 1.090)]:
        f.cameras[name] = CameraFrame(camera=name, stamp=t)
    parts = simultaneous_parts(f, 0.005)
    assert [sorted(p.cameras) for p in parts] == [["cam0", "cam1"], ["cam2", "cam3"], ["cam4"]]
    assert [p.stamp for p in parts] == [1.0, 1.05, 1.09]
    assert parts[0].missing == ["cam7"] and parts[1].missing == [] and parts[2].missing == []
    whole = simultaneous_parts(f, 0.1)
    assert len(whole) == 1 and sorted(whole[0].cameras) == sorted(f.cameras)
