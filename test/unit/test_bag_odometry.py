"""The bag source reads mapping.odometry.topic (nav_msgs/Odometry) into the mapping pipeline, and
names the topic when the bag lacks it. Data: test_11_flips (2 cameras, 5.5 s) plus odometry
messages written next to its detections."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

rosbag = pytest.importorskip("rosbag")

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.config import with_overrides  # noqa: E402
from aruco_ring_localization.errors import ConfigError  # noqa: E402
from aruco_ring_localization.importers import read_rig  # noqa: E402
from aruco_ring_localization.pipeline import MappingPipeline  # noqa: E402
from aruco_ring_localization.schemas import MapperConfig  # noqa: E402

REC = Path(__file__).resolve().parents[2] / "test" / "data" / "tagslam" / "test_11_flips"


def _bag_with_odometry(path: Path, n_bad: int = 1) -> int:
    """The recording's detections plus a straight-line odometry at 20 Hz over their span (and
    ``n_bad`` messages with a NaN quaternion); returns the number of good odometry messages."""
    from nav_msgs.msg import Odometry
    import rospy

    with rosbag.Bag(str(REC / "tag_detections.bag")) as src:
        msgs = list(src.read_messages())
    t0, t1 = min(t.to_sec() for _, _, t in msgs), max(t.to_sec() for _, _, t in msgs)
    good = 0
    with rosbag.Bag(str(path), "w") as out:
        for topic, msg, t in msgs:
            out.write(topic, msg, t)
        for k, s in enumerate(np.arange(t0, t1, 0.05)):
            o = Odometry()
            o.header.stamp = rospy.Time.from_sec(float(s))
            o.header.frame_id, o.child_frame_id = "odom", "imu"
            o.pose.pose.position.x = 0.5 * (s - t0)
            o.pose.pose.orientation.w = 1.0
            if k < n_bad:
                o.pose.pose.orientation.w = float("nan")
            else:
                good += 1
            out.write("/vio/odom", o, rospy.Time.from_sec(float(s)))
    return good


def _pipeline(topic: str) -> MappingPipeline:
    ring = read_rig(str(REC / "cameras.yaml"), camera_poses=str(REC / "camera_poses.yaml")).ring()
    config = with_overrides(MapperConfig(), {"input.use_tf": False, "input.camera_info_fallback": True,
                                             "input.slop": 0.005, "markers.fiducial_len": 0.15,
                                             "mapping.odometry.topic": topic})
    return MappingPipeline(config, ring)


def test_bag_source_feeds_the_odometry_to_the_builder(tmp_path):
    from aruco_ring_localization.ros.bag_source import BagSource

    bag = tmp_path / "walk.bag"
    good = _bag_with_odometry(bag)
    pipe = _pipeline("vio/odom")          # written without the leading slash: the same topic
    with BagSource(str(bag), pipe.input.ring, progress=False, out=open(tmp_path / "log.txt", "w")) as source:
        source.run(pipe, command="test")
    track = pipe.builder.odometry
    assert len(track) == good, f"{len(track)} odometry poses kept of {good} good messages"
    s0 = track._sorted()[0][0]
    A, B = track.pose_at(s0 + 0.33, 0.5), track.pose_at(s0 + 1.33, 0.5)   # between messages: interpolated
    assert A is not None and B is not None and abs(B[0, 3] - A[0, 3] - 0.5) < 1e-6
    assert "odometry from /vio/odom" in (tmp_path / "log.txt").read_text()


def test_bag_source_names_a_missing_odometry_topic(tmp_path):
    from aruco_ring_localization.ros.bag_source import BagSource

    bag = tmp_path / "walk.bag"
    _bag_with_odometry(bag, n_bad=0)
    pipe = _pipeline("/wheel/odom")
    with BagSource(str(bag), pipe.input.ring, progress=False, out=open(tmp_path / "log.txt", "w")) as source:
        with pytest.raises(ConfigError, match=r"/wheel/odom.*\['/vio/odom'\]"):
            source.run(pipe, command="test")
