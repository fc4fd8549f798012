"""``aruco_ring build-map`` on a bag of simulated detections from several stations (needs rosbag: fails without)."""
from __future__ import annotations

from pathlib import Path

import fiducial_msgs.msg as fiducial_msgs
import numpy as np
import pytest
import rosbag
import rospy

from aruco_ring_localization.cli import main  # noqa: E402
from aruco_ring_localization.evaluation.maps import map_error  # noqa: E402
from aruco_ring_localization.marker_map import MarkerMap  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import model_to_camera_info, observations_to_fiducials  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
RING = str(REPO / "config" / "ring.yaml")


@pytest.fixture(scope="module")
def bag_path(tmp_path_factory) -> Path:
    """4 frames at each of the scene's mapping stations, as the ring's topics would record them."""
    scene = Scene.default()
    ring = CameraRing.load(RING)
    sim = RingSimulator(scene, perturb_ring(ring, seed=1), pixel_noise=0.3, seed=5)
    path = tmp_path_factory.mktemp("bag") / "mapping.bag"
    t = 100.0
    with rosbag.Bag(str(path), "w") as bag:
        for station in scene.mapping_stations:
            for _ in range(4):
                frame = sim.observe(Scene.T_world_base(station), t)
                stamp = rospy.Time.from_sec(t)
                for cam in ring.cameras:
                    info = model_to_camera_info(cam.model, cam.frame_id)
                    info.header.stamp = stamp
                    bag.write(f"/{cam.namespace}/camera_info", info, stamp)
                    msg = fiducial_msgs.FiducialArray()
                    msg.header.stamp = stamp
                    msg.header.frame_id = cam.frame_id
                    msg.fiducials = observations_to_fiducials(frame.cameras[cam.name].observations)
                    bag.write(f"/{cam.namespace}/fiducial_vertices", msg, rospy.Time.from_sec(t + 0.01))
                t += 0.1
            t += 5.0  # the robot drives to the next station
    return path


@pytest.mark.parametrize("method, max_rms_mm", [("paper", 40.0), ("refined", 6.0)])
def test_build_map_from_bag(bag_path, tmp_path, method, max_rms_mm):
    out = tmp_path / "map.yaml"
    assert main(["build-map", str(bag_path), "--ring", RING, "--out", str(out), "--method", method]) == 0
    m = MarkerMap.load(str(out))
    truth = Scene.default().truth_map()
    assert sorted(m.ids) == sorted(truth.ids), f"mapped {m.ids}, expected {truth.ids}"
    err = map_error(m, truth, best_fit=True)
    assert err["position_rms_mm"] < max_rms_mm, f"{method}: best-fit RMS {err['position_rms_mm']:.2f} mm"
    assert m.method == method


def test_build_map_frame_option(bag_path, tmp_path, capsys):
    """--frame marker: the reference marker's own frame, recorded in the file; floor (the default
    config's): the reference marker stands upright above the origin."""
    maps = {}
    for frame in ("marker", "floor"):
        out = tmp_path / f"{frame}.yaml"
        assert main(["build-map", str(bag_path), "--ring", RING, "--out", str(out), "--frame", frame]) == 0
        assert f"({frame})" in capsys.readouterr().out
        maps[frame] = MarkerMap.load(str(out))
        assert maps[frame].frame_convention == frame
    ref = maps["marker"].reference_marker
    assert ref == maps["floor"].reference_marker
    np.testing.assert_allclose(maps["marker"][ref].T_map_marker, np.eye(4), atol=1e-9)
    T_floor = maps["floor"][ref].T_map_marker
    assert abs(T_floor[0, 3]) < 1e-9 and abs(T_floor[1, 3]) < 1e-9 and T_floor[2, 3] > 0.1
    # The same map in both frames: the markers' relative poses agree.
    err = map_error(maps["marker"], maps["floor"], best_fit=True)
    assert err["position_rms_mm"] < 1e-6


def test_build_map_without_ring_topics_is_an_error(tmp_path, capsys):
    from aruco_ring_localization.cli import main

    empty = tmp_path / "empty.bag"
    with rosbag.Bag(str(empty), "w"):
        pass
    assert main(["build-map", str(empty), "--out", str(tmp_path / "map.yaml")]) == 1
    err = capsys.readouterr().err
    assert "empty.bag" in err and "fiducial_vertices" in err, err
    assert not (tmp_path / "map.yaml").exists()


def test_build_map_with_anchors(bag_path, tmp_path, capsys):
    """--anchors FILE: the map is in the surveyed frame (the truth's, here) with each anchor's residual,
    printed and in the file; in the strict convention it beats the reference marker's frame."""
    from aruco_ring_localization.anchors import anchors_yaml, noisy_anchors, spread_markers

    truth = Scene.default().truth_map()
    T = {m: truth.T_map_marker(m) for m in truth.ids}
    anchors = tmp_path / "anchors.yaml"
    anchors.write_text(anchors_yaml(noisy_anchors(T, spread_markers(T, 3), 0.001, seed=3)))
    out, ref_out = tmp_path / "map.yaml", tmp_path / "ref.yaml"
    assert main(["build-map", str(bag_path), "--ring", RING, "--out", str(ref_out)]) == 0
    capsys.readouterr()
    assert main(["build-map", str(bag_path), "--ring", RING, "--out", str(out), "--anchors", str(anchors)]) == 0
    text = capsys.readouterr().out
    m = MarkerMap.load(str(out))
    assert m.frame_convention == "survey" and m.anchors["source"] == str(anchors)
    assert "(survey, points)" in text and "sigmas" in text, text
    for p in m.anchors["points"]:
        assert f"{p['marker']:>6} " in text and p["residual_sigmas"] < 5.0, (p, text)
    err, ref_err = map_error(m, truth), map_error(MarkerMap.load(str(ref_out)), truth)
    assert err["position_rms_mm"] < ref_err["position_rms_mm"], \
        f"strict RMS {err['position_rms_mm']:.2f} mm surveyed vs {ref_err['position_rms_mm']:.2f} mm reference"


def test_build_map_places_surveyed_markers_the_bag_never_shows(bag_path, tmp_path, capsys):
    """A surveyed marker with a full pose that the bag never shows is in the map from its survey,
    flagged and printed; one with a position only is named as not mapped; --no-surveyed-unseen
    leaves both out."""
    import yaml

    from aruco_ring_localization.anchors import anchors_yaml, noisy_anchors, spread_markers

    truth = Scene.default().truth_map()
    T = {m: truth.T_map_marker(m) for m in truth.ids}
    data = yaml.safe_load(anchors_yaml(noisy_anchors(T, spread_markers(T, 3), 0.001, seed=3)))
    data["anchors"] += [{"marker": 900, "position": [1.0, 2.0, 1.5], "std": [0.002, 0.002, 0.003],
                         "rotation": [0.5, 0.5, 0.5, 0.5], "rotation_std_deg": 0.5},
                        {"marker": 901, "position": [2.0, 2.0, 1.5], "std": 0.002}]
    anchors = tmp_path / "anchors.yaml"
    anchors.write_text(yaml.safe_dump(data))
    out = tmp_path / "map.yaml"
    assert main(["build-map", str(bag_path), "--ring", RING, "--out", str(out), "--anchors", str(anchors)]) == 0
    text = capsys.readouterr().out
    m = MarkerMap.load(str(out))
    assert m.surveyed_only_ids == [900] and 901 not in m
    assert np.allclose(m.T_map_marker(900)[:3, 3], [1.0, 2.0, 1.5]) and np.allclose(m[900].position_std,
                                                                                      [0.002, 0.002, 0.003])
    assert "surveyed only: 1 surveyed marker(s)" in text and "[900]" in text, text
    assert "   900 never detected: placed from the survey alone" in text, text
    assert "NOT in the map" in text and "[901]" in text, text
    assert main(["build-map", str(bag_path), "--ring", RING, "--out", str(out), "--anchors", str(anchors),
                 "--no-surveyed-unseen"]) == 0
    text = capsys.readouterr().out
    m = MarkerMap.load(str(out))
    assert 900 not in m and m.surveyed_only_ids == [] and "[900, 901]" in text, text


def test_build_map_with_a_bad_anchors_file_names_it(bag_path, tmp_path, capsys):
    anchors = tmp_path / "anchors.yaml"
    anchors.write_text("anchors:\n  - {marker: 17, position: [0, 0, 0], std: 0.001}\n"
                       "  - {marker: 42, position: [1, 0], std: 0.001}\n")
    rc = main(["build-map", str(bag_path), "--ring", RING, "--out", str(tmp_path / "m.yaml"), "--anchors",
               str(anchors)])
    err = capsys.readouterr().err
    assert rc != 0 and str(anchors) in err and "anchors[1].position" in err, err
    assert not (tmp_path / "m.yaml").exists()
