"""FrameGate: the simulator waits for every camera's answer to a frame before the next one."""
from __future__ import annotations

import threading
import time

from aruco_ring_localization.simulation.lockstep import FrameGate


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
