"""``aruco_ring localize`` on a small bag of simulated detections (needs rosbag: skipped without)."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

rosbag = pytest.importorskip("rosbag")
fiducial_msgs = pytest.importorskip("fiducial_msgs.msg")
rospy = pytest.importorskip("rospy")

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.cli import localize  # noqa: E402
from aruco_ring_localization.evaluation.trajectories import read_tum  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import observations_to_fiducials  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _truth(t):
    return np.array([4.5 + 0.1 * t, 4.2, geo.wrap_angle(0.2 * t)])


def test_localize_bag_writes_tum(tmp_path):
    scene = Scene.default()
    ring = CameraRing.load(str(REPO / "config" / "ring.yaml"))
    sim = RingSimulator(scene, perturb_ring(ring, seed=0), pixel_noise=0.3, seed=3)
    bag_path = tmp_path / "det.bag"
    with rosbag.Bag(str(bag_path), "w") as bag:
        for k in range(30):
            t = 50.0 + 0.1 * k
            frame = sim.observe(scene.T_world_base(_truth(t - 50.0)), t)
            for cam in ring.cameras:
                msg = fiducial_msgs.FiducialArray()
                msg.header.stamp = rospy.Time.from_sec(t)
                msg.header.frame_id = cam.frame_id
                msg.fiducials = observations_to_fiducials(frame.cameras[cam.name].observations)
                bag.write(f"/{cam.namespace}/fiducial_vertices", msg, rospy.Time.from_sec(t + 0.01))
    out = tmp_path / "traj.tum"
    csv_path = tmp_path / "diag.csv"
    args = argparse.Namespace(bag=str(bag_path), ring=str(REPO / "config" / "ring.yaml"),
                              map_file=str(REPO / "test" / "data" / "lab_truth_map.yaml"), out=str(out),
                              fusion="joint", csv=str(csv_path), slop=0.03)
    assert localize.run(args) == 0
    traj = read_tum(str(out))
    assert traj.num_poses == 30, f"expected 30 poses, got {traj.num_poses}"
    for t, xyz in zip(traj.timestamps, traj.positions_xyz):
        truth = _truth(t - 50.0)
        err = np.hypot(xyz[0] - truth[0], xyz[1] - truth[1])
        assert err < 0.03, f"t={t:.2f}: position error {err * 100:.2f} cm"
    assert csv_path.read_text().count("\n") == 31


def test_localize_bad_map_is_an_error(tmp_path):
    bad = tmp_path / "map.yaml"
    bad.write_text("markers: 3\n")
    args = argparse.Namespace(bag=str(tmp_path / "none.bag"), ring=str(REPO / "config" / "ring.yaml"),
                              map_file=str(bad), out=str(tmp_path / "t.tum"), fusion="paper", csv=None, slop=0.03)
    assert localize.run(args) == 1
