"""aruco_ring export-tum: pose topics of the three types and a tf chain, back as the poses written."""
from __future__ import annotations

import numpy as np
import pytest
import rosbag
import rospy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from tf2_msgs.msg import TFMessage

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.cli import main
from aruco_ring_localization.evaluation.trajectories import read_tum
from aruco_ring_localization.ros.conversions import make_transform_stamped, pose_to_msg


def _truth(k):
    return geo.transform_from_se2(0.1 * k, 2.0 - 0.05 * k, 0.03 * k)


def _odom_drift(k):
    return geo.transform_from_se2(0.01 * k, -0.02, 0.002 * k)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("export") / "ref.bag")
    with rosbag.Bag(path, "w") as b:
        t0 = 100.0
        static = TFMessage([make_transform_stamped(geo.transform_from_se2(0.2, 0, 0), "base_link", "laser",
                                                  rospy.Time.from_sec(t0))])
        b.write("/tf_static", static, rospy.Time.from_sec(t0))
        for k in range(20):
            t = rospy.Time.from_sec(t0 + 0.1 * k)
            ps = PoseStamped()
            ps.header.stamp, ps.header.frame_id, ps.pose = t, "world", pose_to_msg(_truth(k))
            b.write("/sim/ground_truth", ps, t)
            pc = PoseWithCovarianceStamped()
            pc.header.stamp, pc.pose.pose = t, pose_to_msg(_truth(k))
            b.write("/amcl_pose", pc, t)
            od = Odometry()
            od.header.stamp, od.pose.pose = t, pose_to_msg(_truth(k))
            b.write("/odometry/filtered", od, t)
            # gmapping's pose as tf: map -> odom (slow) composed with odom -> base_link
            T_odom_base = _odom_drift(k)
            tfs = [make_transform_stamped(T_odom_base, "/odom", "base_link", t)]
            if k % 4 == 0 or k > 1:
                tfs.append(make_transform_stamped(_truth(k) @ geo.inverse(T_odom_base), "map", "odom", t))
            b.write("/tf", TFMessage(tfs), t)
        bad = PoseStamped()
        bad.header.stamp = rospy.Time.from_sec(t0 + 5.0)   # zero quaternion: invalid, skipped
        b.write("/sim/ground_truth", bad, bad.header.stamp)
    return path


@pytest.mark.parametrize("topic", ["/sim/ground_truth", "amcl_pose", "/odometry/filtered"])
def test_pose_topics_come_back_as_written(bag, tmp_path, topic, capsys):
    out = tmp_path / "ref.tum"
    assert main(["export-tum", bag, "--topic", topic, "--out", str(out)]) == 0
    traj = read_tum(str(out))
    assert len(traj.timestamps) == 20
    assert np.allclose(traj.timestamps, 100.0 + 0.1 * np.arange(20), atol=1e-6)
    for k, T in enumerate(traj.poses_se3):
        assert np.allclose(T, _truth(k), atol=1e-9)
    err = capsys.readouterr().err
    if topic == "/sim/ground_truth":
        assert "1 invalid messages skipped" in err, err


def test_tf_chain_is_composed_at_each_stamp(bag, tmp_path):
    out = tmp_path / "gm.tum"
    assert main(["export-tum", bag, "--tf", "map", "base_link", "--out", str(out)]) == 0
    traj = read_tum(str(out))
    # k = 0 .. 19 all have map -> odom at their own stamp but k = 1 (interpolated between 0 and 2)
    assert len(traj.timestamps) == 20
    for t, T in zip(traj.timestamps, traj.poses_se3):
        k = int(round((t - 100.0) / 0.1))
        if k != 1:
            assert np.allclose(T, _truth(k), atol=1e-6), k


def test_clear_errors(bag, capsys):
    assert main(["export-tum", bag, "--topic", "/nope"]) == 1
    assert "no topic /nope" in capsys.readouterr().err
    assert main(["export-tum", bag, "--topic", "/tf"]) == 1
    assert "tf2_msgs/TFMessage, not one of" in capsys.readouterr().err
    assert main(["export-tum", bag, "--tf", "map", "nowhere"]) == 1
    assert "no frame nowhere" in capsys.readouterr().err
