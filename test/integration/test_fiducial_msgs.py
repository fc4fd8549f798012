"""Our fiducial_msgs must be wire-compatible with the public fiducial_msgs 0.12.

ROS matches publishers and subscribers by md5sum, computed from the field lists; equal
md5sums mean a robot running the real aruco_detect talks to our nodes unchanged. The expected
values are those of the public package's generated code. Needs the built workspace
(``source .ws/env.sh``), no master.
"""
from __future__ import annotations

import importlib

import pytest

PUBLIC_MD5 = {
    "fiducial_msgs.msg.Fiducial": "a0094064db6c7772c6b638a2dab17f42",
    "fiducial_msgs.msg.FiducialArray": "fd851a0658e8a35a4d4f80b76d9f17a0",
    "fiducial_msgs.msg.FiducialTransform": "9f77f4c92fda876d2249ffbc19859044",
    "fiducial_msgs.msg.FiducialTransformArray": "a9391b25df2859cb1ae6fa6ee45ef075",
    "fiducial_msgs.msg.FiducialMapEntry": "2dc3e2ac5967f3a2c19627a1fc1d7dcc",
    "fiducial_msgs.msg.FiducialMapEntryArray": "f3d7e1cb2717bda61be54acdb77f4f79",
    "fiducial_msgs.srv.InitializeMap": "af3be60cc8712d87e234a795a01490e4",
}


def _load(dotted: str):
    module_name, _, name = dotted.rpartition(".")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        pytest.fail(f"cannot import {module_name} ({exc}): run `make setup` and `source .ws/env.sh`")
    return getattr(module, name)


@pytest.mark.parametrize("dotted", sorted(PUBLIC_MD5), ids=lambda d: d.rsplit(".", 1)[-1])
def test_md5sum_matches_public_fiducial_msgs(dotted: str):
    cls = _load(dotted)
    assert cls._md5sum == PUBLIC_MD5[dotted], (
        f"{cls._type}: md5sum {cls._md5sum} differs from the public fiducial_msgs' {PUBLIC_MD5[dotted]}: "
        f"a field's name, type or order changed")
