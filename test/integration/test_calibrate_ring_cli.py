"""``aruco_ring calibrate-ring`` on a bag of the simulated lab: the robot turns on the spot, drives,
turns again; the ring file given is the true rig off by up to 5 cm and 10 deg per camera (seeded).
The bag is written here from the simulator (corners mode: fiducial_vertices, camera_info, odom)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import fiducial_msgs.msg as fiducial_msgs
import numpy as np
import pytest
import rosbag
import rospy
import yaml
from nav_msgs.msg import Odometry

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.cli import main
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import model_to_camera_info, observations_to_fiducials, pose_to_msg
from aruco_ring_localization.simulation.calibration_run import calibration_poses, odometry_poses, rough_ring
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

RING = Path(__file__).resolve().parents[2] / "config" / "ring.yaml"


def _write_bag(path, sim: RingSimulator, ring: CameraRing, poses, odom) -> None:
    with rosbag.Bag(str(path), "w") as bag:
        for k, pose in enumerate(poses):
            t = 1.0 + 0.1 * k
            frame = sim.observe(Scene.T_world_base(pose), t)
            if odom is not None:
                msg = Odometry()
                msg.header.stamp = rospy.Time.from_sec(t)
                msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
                msg.pose.pose = pose_to_msg(odom[k])
                bag.write("/odom", msg, rospy.Time.from_sec(t))
            for cam in ring.cameras:
                if k == 0:
                    bag.write(f"/{cam.namespace}/camera_info", model_to_camera_info(cam.model, cam.frame_id),
                              rospy.Time.from_sec(t))
                msg = fiducial_msgs.FiducialArray()
                msg.header.stamp = rospy.Time.from_sec(t)
                msg.header.frame_id = cam.frame_id
                msg.fiducials = observations_to_fiducials(frame.cameras[cam.name].observations)
                bag.write(f"/{cam.namespace}/fiducial_vertices", msg, rospy.Time.from_sec(t + 0.01))


def _errors(true: CameraRing, est: CameraRing):
    """(max mm, max deg) camera by camera, and the same relative to the ring (best-fit common motion removed)."""
    def err(a, b):
        D = geo.inverse(a) @ b
        return 1000 * np.linalg.norm(D[:3, 3]), np.degrees(geo.rotation_angle(D[:3, :3]))
    direct = np.array([err(c.T_base_cam, est[c.name].T_base_cam) for c in true])
    G = geo.average_transforms([c.T_base_cam @ geo.inverse(est[c.name].T_base_cam) for c in true])
    rel = np.array([err(c.T_base_cam, G @ est[c.name].T_base_cam) for c in true])
    return direct.max(axis=0), rel.max(axis=0), direct


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("calib")
    ring = CameraRing.load(str(RING))
    true = perturb_ring(ring, seed=1)
    rough = rough_ring(true, seed=5)
    rough_path = tmp / "rough.yaml"
    rough.save(str(rough_path))
    scene = Scene.default()
    poses = calibration_poses(scene.mapping_stations[:3], turn_step_deg=6.0, drive_step=0.1)
    sim = RingSimulator(scene, true, pixel_noise=0.3, seed=0)
    bag = tmp / "calib.bag"
    _write_bag(bag, sim, ring, poses, odometry_poses(poses, seed=2))
    return tmp, true, rough, rough_path, bag


def test_calibrate_ring_from_rough_values_with_odometry(lab, capsys):
    tmp, true, rough, rough_path, bag = lab
    out = tmp / "ring.yaml"
    assert main(["calibrate-ring", str(bag), "--ring", str(rough_path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    est = CameraRing.load(str(out))
    before, _, _ = _errors(true, rough)
    direct, rel, per_cam = _errors(true, est)
    assert before[0] > 20 and before[1] > 5, before          # the start really is rough
    # Relative to each other: the motion and the markers determine them.
    assert rel[0] < 1.0 and rel[1] < 0.05, rel
    # Directly against base_link: only the height is not observable (planar motion): it is said.
    assert direct[1] < 0.1, direct
    dz = [1000 * (est[c.name].T_base_cam[2, 3] - c.T_base_cam[2, 3]) for c in true]
    assert np.ptp(dz) < 1.0, dz
    horizontal = [1000 * np.linalg.norm(est[c.name].T_base_cam[:2, 3] - c.T_base_cam[:2, 3]) for c in true]
    assert max(horizontal) < 1.0, horizontal
    assert "planar motion only" in text and "no odometry" not in text, text
    # The file: the ring format with per-camera std, written atomically (readable, complete).
    data = yaml.safe_load(out.read_text())
    stds = [c["extrinsics_std"] for c in data["cameras"]]
    assert all(0 < max(s["translation"]) < 0.002 and 0 < max(s["rotation_deg"]) < 0.05 for s in stds), stds


def test_calibrate_ring_without_odometry_warns_about_the_heading(lab, capsys):
    tmp, true, rough, rough_path, bag = lab
    out = tmp / "ring_noodom.yaml"
    assert main(["calibrate-ring", str(bag), "--ring", str(rough_path), "--out", str(out), "--odom", "none"]) == 0
    text = capsys.readouterr().out
    _, rel, _ = _errors(true, CameraRing.load(str(out)))
    assert rel[0] < 1.0 and rel[1] < 0.05, rel
    assert "no odometry: base_link's heading" in text, text


def test_calibrate_ring_honours_a_declared_wiggle_unless_told_off(lab, capsys):
    """A rough ring declaring two cameras' wiggle: by default their fixed poses are calibrated (and
    the declaration written back, the line says so); ``--wiggle off``: the rigid calibration. The lab's
    ring is rigid: both agree with it."""
    tmp, true, rough, rough_path, bag = lab
    wiggling = ("cam0", "cam1")
    declared = CameraRing([replace(c, wiggle=(np.radians(0.2), 0.002) if c.name in wiggling else None) for c in rough],
                          rough.base_frame)
    declared_path = tmp / "rough_wiggle.yaml"
    declared.save(str(declared_path))
    off, auto = tmp / "ring_wiggle_off.yaml", tmp / "ring_wiggle_auto.yaml"
    assert main(["calibrate-ring", str(bag), "--ring", str(declared_path), "--out", str(off), "--wiggle", "off"]) == 0
    assert "wiggle:" not in capsys.readouterr().out
    assert main(["calibrate-ring", str(bag), "--ring", str(declared_path), "--out", str(auto)]) == 0
    text = capsys.readouterr().out
    assert "wiggle: cam0, cam1 declare" in text and "--wiggle off" in text, text
    est_off, est = CameraRing.load(str(off)), CameraRing.load(str(auto))
    assert all((c.wiggle == pytest.approx((np.radians(0.2), 0.002))) if c.name in wiggling else c.wiggle is None
               for c in est)
    _, rel_off, _ = _errors(true, est_off)
    _, rel, _ = _errors(true, est)
    assert rel_off[0] < 1.0 and rel_off[1] < 0.05, rel_off
    assert rel[0] < 1.0 and rel[1] < 0.05, rel
    with pytest.raises(SystemExit):
        main(["calibrate-ring", str(bag), "--ring", str(declared_path), "--out", str(auto), "--wiggle", "on"])
