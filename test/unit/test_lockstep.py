"""FrameGate: the simulator waits for every consumer's answer to a frame before the next one; SimClock."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from aruco_ring_localization.simulation.lockstep import FrameGate, SimClock


def test_returns_at_once_when_every_source_answered():
    gate = FrameGate(["cam0", "cam1"])
    gate.report("cam0", 1.0)
    gate.report("cam1", 1.2)          # newer than the frame: it answered this one too
    gate.report("cam9", 0.0)          # not waited for: ignored
    t0 = time.monotonic()
    assert gate.wait(1.0, timeout=5.0) == []
    assert time.monotonic() - t0 < 1.0


def test_times_out_naming_the_silent_source():
    gate = FrameGate(["cam0", "cam1"])
    gate.report("cam0", 2.0)
    gate.report("cam1", 1.9)          # an older frame's answer does not count
    t0 = time.monotonic()
    assert gate.wait(2.0, timeout=0.2) == ["cam1"]
    waited = time.monotonic() - t0
    assert 0.15 < waited < 2.0, f"waited {waited:.2f} s for a 0.2 s timeout"
    gate.report("cam0", 1.0)          # an old stamp never moves a source back
    assert gate.missing(2.0) == ["cam1"]


def test_wakes_up_when_the_last_answer_arrives_from_another_thread():
    gate = FrameGate(["a", "b"])
    gate.report("a", 5.0)
    threading.Timer(0.1, gate.report, args=("b", 5.0)).start()
    t0 = time.monotonic()
    assert gate.wait(5.0, timeout=10.0) == []
    waited = time.monotonic() - t0
    assert waited < 5.0, f"woke up after {waited:.2f} s"


def test_only_the_active_sources_are_waited_for_and_idle_is_called():
    gate = FrameGate(["det", "localizer/pose"])
    gate.report("det", 3.0)
    connected = ["det"]                      # the localizer is not running: not waited for
    idle = []
    assert gate.wait(3.0, timeout=5.0, active=lambda: connected, idle=idle.append) == []
    connected.append("localizer/pose")       # it connected: now it is
    t0 = time.monotonic()
    assert gate.wait(3.0, timeout=0.3, active=lambda: connected, idle=idle.append,
                     idle_period=0.02) == ["localizer/pose"]
    assert 0.25 < time.monotonic() - t0 < 3.0
    assert len(idle) >= 5 and idle == sorted(idle) and idle[-1] < 0.5, idle
    gate.reset()                              # after a clock jump back, old answers do not count
    assert gate.missing(1.0) == ["det", "localizer/pose"]


def test_sim_clock_frames_jumps_and_creep():
    clock = SimClock(start=1.0, dt=0.1)
    assert clock.creep(1.0) == 1.0                       # before the first frame: the start time
    times = [clock.advance() for _ in range(30)]
    assert times[0] == 1.0 and times[-1] == 3.9          # from the frame count: no accumulated rounding
    assert np.allclose(np.diff(times), 0.1, atol=1e-12)
    # Creeping while the consumers of the frame at 3.9 s are busy: slowly, never up to the next frame.
    assert clock.creep(0.0) == 3.9
    assert 3.9 < clock.creep(0.1) < clock.creep(0.2) < 4.0
    assert clock.creep(100.0) == pytest.approx(3.9 + 0.4 * 0.1)
    clock.request_jump(-2.0)                              # a bag loop: the next frame is 2 s earlier
    assert clock.advance() == pytest.approx(2.0)
    assert clock.advance() == pytest.approx(2.1)
    clock.request_jump(-50.0)                             # below zero: refused
    assert clock.advance() == pytest.approx(2.2)
