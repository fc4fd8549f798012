#!/usr/bin/env python3
"""rostest node for simulator_lockstep_topic.test: lockstep on a downstream topic (consumer/pose).

This node is a slow consumer: 30 ms after each ground-truth message it answers with the same
stamp on ``consumer/pose``. The simulator asked for 50x real time (5 ms per frame), so without the
lockstep the frames would come six times faster than the answers.
"""
from __future__ import annotations

import threading
import time
import unittest

import numpy as np
import rospy
import rostest
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rosgraph_msgs.msg import Clock

PKG = "aruco_ring_localization"
RATE = 10.0
ANSWER_DELAY = 0.03


class LockstepTopicTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("simulator_lockstep_topic_rostest")
        cls.frames = int(rospy.get_param("~frames", 40))
        cls.lock = threading.Lock()
        cls.truth, cls.clock = [], []
        cls.answered = {}   # frame stamp -> time.monotonic() just before its answer was published
        cls.pub = rospy.Publisher("consumer/pose", PoseWithCovarianceStamped, queue_size=10)
        rospy.Subscriber("/clock", Clock, cls._on_clock, queue_size=1000)
        rospy.Subscriber("sim/ground_truth", PoseStamped, cls._on_truth, queue_size=100)

    @classmethod
    def _on_clock(cls, msg):
        with cls.lock:
            cls.clock.append((time.monotonic(), msg.clock.to_sec()))

    @classmethod
    def _on_truth(cls, msg):
        with cls.lock:
            cls.truth.append(msg.header.stamp.to_sec())
        time.sleep(ANSWER_DELAY)
        answer = PoseWithCovarianceStamped()
        answer.header.stamp = msg.header.stamp
        answer.pose.pose = msg.pose
        with cls.lock:
            cls.answered[round(msg.header.stamp.to_sec() * RATE)] = time.monotonic()
        cls.pub.publish(answer)

    def test_each_frame_waits_for_the_answer_to_the_previous_one(self):
        end = time.monotonic() + 60.0
        while time.monotonic() < end and not rospy.is_shutdown():
            with self.lock:
                if len(self.truth) >= self.frames:
                    break
            time.sleep(0.05)
        with self.lock:
            stamps = np.array(self.truth)
            clock = np.array(self.clock)
        self.assertGreaterEqual(len(stamps), self.frames, f"only {len(stamps)} frames in 60 s")
        steps = np.round(np.diff(stamps) * RATE, 6)
        self.assertTrue(np.all(steps == 1.0), f"frames skipped or repeated: steps {sorted(set(steps))} frames")
        # Each frame's clock tick comes only after the previous frame was answered. Causally: the
        # tick is received after the answer's publish began (recorded just before it), whatever the
        # load does to the callbacks' timing (a gap between two received ticks is not: a tick
        # received late and the next on time look closer than they were sent).
        ticks = clock[np.abs(clock[:, 1] * RATE - np.round(clock[:, 1] * RATE)) < 1e-6]
        ticks = ticks[(ticks[:, 1] > stamps[0] + 0.5 / RATE) & (ticks[:, 1] <= stamps[-1])]
        first_tick = {}
        for t_recv, c in ticks:
            first_tick.setdefault(int(round(c * RATE)), t_recv)
        with self.lock:
            answered = dict(self.answered)
        pairs = [(k, first_tick[k], answered[k - 1]) for k in sorted(first_tick) if k - 1 in answered]
        self.assertGreater(len(pairs), self.frames // 2, f"only {len(pairs)} frame ticks after an answer seen")
        early = [(k, 1000 * (t_ans - t_tick)) for k, t_tick, t_ans in pairs if t_tick <= t_ans]
        self.assertFalse(early, f"frames whose clock tick came before the previous frame's answer "
                                f"(frame, ms early): {early[:5]}")
        # While waiting the clock creeps: ticks strictly between two frames, never reaching the next.
        between = [c for _, c in clock if stamps[0] < c < stamps[-1] and abs(c * RATE - round(c * RATE)) > 1e-6]
        self.assertTrue(between, "the clock never moved between two frames")
        for c in between:
            nxt = stamps[np.searchsorted(stamps, c)]
            self.assertLess(c, nxt - 0.5 / RATE, f"the clock crept to {c:.4f} s, too close to the next frame {nxt}")

if __name__ == "__main__":
    rostest.rosrun(PKG, "simulator_lockstep_topic", LockstepTopicTest)
