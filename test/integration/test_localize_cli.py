"""``aruco_ring localize`` on a small bag of simulated detections (needs rosbag: fails without)."""
from __future__ import annotations

import csv
from pathlib import Path

import fiducial_msgs.msg as fiducial_msgs
import numpy as np
import rosbag
import rospy

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.cli import main  # noqa: E402
from aruco_ring_localization.evaluation.trajectories import read_tum as _read_trajectory  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import observations_to_fiducials  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _truth(t):
    return np.array([4.5 + 0.1 * t, 4.2, geo.wrap_angle(0.2 * t)])


def read_tum(path: str) -> np.ndarray:
    """(N, 8) rows t x y z qx qy qz qw of a TUM file (read through evo)."""
    traj = _read_trajectory(path)
    q = traj.orientations_quat_wxyz
    return np.column_stack([traj.timestamps, traj.positions_xyz, q[:, 1:], q[:, :1]])


def test_localize_bag_writes_tum(tmp_path, capsys):
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
                # The namespace written three ways: the bag source accepts each.
                topic = [f"/{cam.namespace}", f"{cam.namespace}", f"/{cam.namespace}/"][k % 3].rstrip("/")
                bag.write(f"{topic}/fiducial_vertices", msg, rospy.Time.from_sec(t + 0.01))
    out = tmp_path / "traj.tum"
    csv_path = tmp_path / "diag.csv"
    assert main(["localize", str(bag_path), "--ring", str(REPO / "config" / "ring.yaml"),
                 "--map", str(REPO / "test" / "data" / "lab_truth_map.yaml"), "--out", str(out),
                 "--fusion", "joint", "--csv", str(csv_path)]) == 0
    err = capsys.readouterr().err
    assert "8 from the ring file" in err and "no camera_info in the bag" in err, err
    traj = read_tum(str(out))
    assert traj.shape == (30, 8), f"expected 30 poses, got {traj.shape}"
    for row in traj:
        truth = _truth(row[0] - 50.0)
        err = np.hypot(row[1] - truth[0], row[2] - truth[1])
        assert err < 0.03, f"t={row[0]:.2f}: position error {err * 100:.2f} cm"
    rows = list(csv.DictReader(open(csv_path)))
    assert len(rows) == 30 and np.allclose([float(r["stamp"]) for r in rows], traj[:, 0], atol=1e-6, rtol=0)
    assert abs(float(rows[-1]["x"]) - traj[-1, 1]) < 1e-6


def test_localize_measurement_6dof(tmp_path):
    scene = Scene.default()
    ring = CameraRing.load(str(REPO / "config" / "ring.yaml"))
    sim = RingSimulator(scene, ring, pixel_noise=0.3, seed=3)
    bag_path = tmp_path / "det.bag"
    with rosbag.Bag(str(bag_path), "w") as bag:
        for k in range(5):
            t = 10.0 + 0.1 * k
            frame = sim.observe(scene.T_world_base(_truth(0.0)), t)
            for cam in ring.cameras:
                msg = fiducial_msgs.FiducialArray()
                msg.header.stamp = rospy.Time.from_sec(t)
                msg.header.frame_id = cam.frame_id
                msg.fiducials = observations_to_fiducials(frame.cameras[cam.name].observations)
                bag.write(f"/{cam.namespace}/fiducial_vertices", msg, rospy.Time.from_sec(t + 0.01))
    out = tmp_path / "meas.tum"
    assert main(["localize", str(bag_path), "--map", str(REPO / "test" / "data" / "lab_truth_map.yaml"),
                 "--out", str(out), "--output", "measurement", "--6dof", "--ignore-fiducials", "17"]) == 0
    traj = read_tum(str(out))
    assert traj.shape == (5, 8)
    T = scene.T_world_base(_truth(0.0))
    for row in traj:
        assert np.hypot(row[1] - T[0, 3], row[2] - T[1, 3]) < 0.01 and abs(row[3] - T[2, 3]) < 0.01, row


def test_localize_bad_map_is_an_error(tmp_path):
    bad = tmp_path / "map.yaml"
    bad.write_text("markers: 3\n")
    assert main(["localize", str(tmp_path / "none.bag"), "--map", str(bad), "--out", str(tmp_path / "t.tum"),
                 "--fusion", "paper"]) == 1
