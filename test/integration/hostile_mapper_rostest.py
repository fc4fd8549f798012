#!/usr/bin/env python3
"""rostest node of hostile_mapper.test: what the mapper's files look like after many saves.

The issue (F7): saved maps were mode 0600 (a localizer run as another user could not read them),
and one ``.bak`` generation only (a 9-marker save rotated the 10-marker backup away). Here the
mapper's ``~save_map`` is called SAVES times: the map and ``map/backups`` (5) generations
``map.yaml.bak``, ``.bak.2`` ... ``.bak.5`` must exist, each a loadable map, all with the mode the
umask gives a new file; then ``~clear`` and a ``~save_map`` (of the few frames since the clear, or
of nothing) must leave the map saved before the clear recoverable as the newest backup. Named ``*_rostest.py`` so pytest does not collect it.
"""
from __future__ import annotations

import hashlib
import os
import time
import unittest

import rospy
import rostest
from std_srvs.srv import Trigger

from aruco_ring_localization.fileio import backup_paths
from aruco_ring_localization.marker_map import MarkerMap

PKG = "aruco_ring_localization"
SAVES = 7
BACKUPS = 5   # map/backups in config/mapping.yaml


def _digest(path: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


class HostileMapper(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("hostile")
        cls.path = rospy.get_param("/mapper/map_file")
        cls.backups = int(rospy.get_param("/mapper/map/backups"))
        rospy.wait_for_service("/mapper/save_map", timeout=60)
        save = rospy.ServiceProxy("/mapper/save_map", Trigger)
        cls.clear = rospy.ServiceProxy("/mapper/clear", Trigger)
        deadline = time.monotonic() + 90
        cls.results = []
        while len(cls.results) < SAVES and time.monotonic() < deadline:
            r = save()
            if r.success:
                cls.results.append(r.message)
            rospy.rostime.wallsleep(0.5)
        umask = os.umask(0)
        os.umask(umask)
        cls.expected_mode = 0o666 & ~umask
        cls.before = _digest(cls.path)
        cls.clear()
        cls.save_after_clear = save()

    def test_1_every_save_succeeded(self):
        self.assertEqual(len(self.results), SAVES, f"only {len(self.results)} saves succeeded")
        self.assertEqual(self.backups, BACKUPS)

    def test_2_the_backups_are_there_newest_first_and_loadable(self):
        paths = backup_paths(self.path, self.backups)
        missing = [p for p in paths if not os.path.exists(p)]
        self.assertFalse(missing, f"after {SAVES} saves: {missing} missing")
        self.assertFalse(os.path.exists(f"{self.path}.bak.{self.backups + 1}"))
        mtimes = [os.path.getmtime(p) for p in [self.path] + paths]
        self.assertEqual(mtimes, sorted(mtimes, reverse=True), "backups not newest first")
        for p in [self.path] + paths:
            self.assertGreater(len(MarkerMap.load(p)), 0, p)

    def test_3_modes_follow_the_umask(self):
        modes = {p: oct(os.stat(p).st_mode & 0o777) for p in [self.path] + backup_paths(self.path, self.backups)}
        self.assertEqual(set(modes.values()), {oct(self.expected_mode)}, modes)

    def test_4_a_save_after_clear_keeps_the_previous_map_recoverable(self):
        newest = self.path if not self.save_after_clear.success else backup_paths(self.path, 1)[0]
        self.assertEqual(_digest(newest), self.before, f"the map saved before ~clear is not {newest} "
                                                       f"({self.save_after_clear.message})")


if __name__ == "__main__":
    rostest.rosrun(PKG, "hostile_mapper", HostileMapper)
