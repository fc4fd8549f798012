"""MapBuilder: the paper's mode, the reference rule, multi-station linking (malformed inputs: test_pipeline.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.evaluation.maps import map_error
from aruco_ring_localization.detections import CameraFrame, MarkerObservation, RingFrame
from aruco_ring_localization.mapping import MapBuilder, MappingOptions
from aruco_ring_localization.pnp import solve_marker_ippe_undistorted
from aruco_ring_localization.markers import MarkerSizes, marker_corners
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Scene, SceneMarker, marker_pose


def _frames(sim, poses, n, t0=0.0):
    t = t0
    for pose in poses:
        for _ in range(n):
            yield sim.observe(Scene.T_world_base(pose), stamp=t)
            t += 0.1


def test_paper_mode_exact_on_noise_free_corners(ring, scene):
    sim = RingSimulator(scene, ring, pixel_noise=0.0, seed=0)
    b = MapBuilder(ring, MarkerSizes(0.2), method="paper")
    for f in _frames(sim, [scene.mapping_pose], 2):
        b.add_frame(f)
    m = b.build()
    err = map_error(m, scene.truth_map())
    assert err["n"] == len(scene.markers), f"mapped {m.ids}, missing {err['missing']}"
    assert err["position_max_mm"] < 1e-3, f"max position error {err['position_max_mm']:.2e} mm"
    assert err["rotation_max_deg"] < 1e-4, f"max rotation error {err['rotation_max_deg']:.2e} deg"
    ref = m[m.reference_marker].T_map_marker
    assert abs(ref[0, 3]) < 1e-9 and abs(ref[1, 3]) < 1e-9, f"reference not above the origin: {ref[:3, 3]}"


def test_reference_follows_the_papers_rule(ring):
    """Closest to its camera and most face-on wins; a user's reference overrides."""
    cam = ring["cam0"]
    T_base_cam = cam.T_base_cam
    # Three markers in front of cam0: near & face-on (1), nearer but oblique 60 deg (2), far & face-on (3).
    poses = {1: geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]), [0.0, 0.0, 2.0]),
             2: geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]) @ geo.rotation_from_rvec([0, np.radians(60), 0]),
                                   [-0.6, 0.0, 1.6]),
             3: geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]), [0.7, 0.0, 4.0])}
    obs = [MarkerObservation(i, cam.model.project(geo.transform_points(T, marker_corners(0.2))))
           for i, T in poses.items()]
    frame = RingFrame(0.0, {"cam0": CameraFrame("cam0", 0.0, obs)})
    b = MapBuilder(ring, MarkerSizes(0.2), method="paper")
    b.add_frame(frame)
    assert b.reference == 1, f"reference {b.reference}, expected 1 (near, face-on)"
    assert b.build().reference_marker == 1
    b2 = MapBuilder(ring, MarkerSizes(0.2), method="paper", reference_marker=3)
    b2.add_frame(frame)
    m = b2.build()
    assert m.reference_marker == 3
    # Chaining is the same whatever the reference: marker 1 relative to 3 matches the truth.
    T31 = geo.inverse(m.T_map_marker(3)) @ m.T_map_marker(1)
    dp, dr = geo.pose_distance(T31, geo.inverse(poses[3]) @ poses[1])
    assert dp < 1e-6 and dr < 1e-6, f"relative pose error {dp:.2e} m, {dr:.2e} rad"
    del T_base_cam


def test_refined_reduces_map_error_on_noisy_multi_station(ring, scene):
    from aruco_ring_localization.simulation.ring_sim import perturb_ring

    true_ring = perturb_ring(ring, seed=1)
    sim = RingSimulator(scene, true_ring, pixel_noise=0.3, seed=2)
    b = MapBuilder(ring, MarkerSizes(0.2))
    for f in _frames(sim, scene.mapping_stations, 6):
        b.add_frame(f)
    assert b.station_count == len(scene.mapping_stations), f"{b.station_count} stations detected"
    truth = scene.truth_map()
    paper = map_error(b.build("paper"), truth, best_fit=True)
    refined_map = b.build("refined")
    refined = map_error(refined_map, truth, best_fit=True)
    assert refined["n"] == len(scene.markers)
    assert refined["position_rms_mm"] < 0.5 * paper["position_rms_mm"], \
        f"refined RMS {refined['position_rms_mm']:.2f} mm vs paper {paper['position_rms_mm']:.2f} mm"
    # The target for a refined map on the lab is 3 mm RMS (docs/mapping.md); this configuration
    # measured 1.55, 1.82 and 2.37 mm for rig/noise seeds 1, 2, 3.
    assert refined["position_rms_mm"] < 3.0, f"refined RMS {refined['position_rms_mm']:.2f} mm (target 3 mm)"
    stds = np.array([np.max(e.position_std) for e in refined_map if e.marker_id != refined_map.reference_marker])
    assert np.all(stds > 0) and np.all(stds < 0.05), f"position std (m) {stds}"
    # The map carries the refined ring calibration, and it is closer to the true rig than the file's.
    assert sorted(refined_map.ring_extrinsics) == sorted(ring.names)
    before = [np.degrees(geo.pose_distance(ring[c].T_base_cam, true_ring[c].T_base_cam)[1]) for c in ring.names]
    after = [np.degrees(geo.pose_distance(refined_map.ring_extrinsics[c], true_ring[c].T_base_cam)[1])
             for c in ring.names]
    assert np.mean(after) < 0.5 * np.mean(before), \
        f"mean extrinsic rotation error {np.mean(after):.3f} deg refined vs {np.mean(before):.3f} deg in the ring file"


def test_disconnected_marker_is_reported(ring, scene):
    """A marker seen only from a station that shares nothing with the mapped set is not dropped silently."""
    far = SceneMarker(999, marker_pose([30.0, 4.5, 1.0], np.pi), 0.2)
    big = Scene(**{**scene.__dict__, "markers": list(scene.markers) + [far]})
    big.room = type(scene.room)(origin=(0.0, 0.0), size=(40.0, 9.0), height=3.0)
    sim = RingSimulator(big, ring, pixel_noise=0.0, seed=0, max_range=8.0)
    b = MapBuilder(ring, MarkerSizes(0.2))
    for f in _frames(sim, [scene.mapping_pose], 2):
        b.add_frame(f)
    for f in _frames(sim, [(27.0, 4.5, 0.0)], 2, t0=10.0):
        b.add_frame(f)
    assert 999 in b.seen, "the far marker should have been detected"
    assert b.unlinked_markers() == [999], f"unlinked {b.unlinked_markers()}"
    assert 999 not in b.build("paper")
    assert 999 in b.summary()["unlinked"]


def test_marker_with_wrong_size_rejected(ring, scene):
    """Marker 42 is printed at 0.16 m while the map believes 0.2 m: stations disagree, it is rejected."""
    markers = [SceneMarker(m.marker_id, m.T_world_marker, 0.16 if m.marker_id == 42 else m.size)
               for m in scene.markers]
    sim = RingSimulator(Scene(**{**scene.__dict__, "markers": markers}), ring, pixel_noise=0.0, seed=0)
    b = MapBuilder(ring, MarkerSizes(0.2))
    for f in _frames(sim, scene.mapping_stations, 1):
        b.add_frame(f)
    m = b.build("paper")
    assert 42 not in m and 42 in b.rejected_markers(), f"rejected {b.rejected_markers()}"
    assert "size" in b.rejected_markers()[42]
    # With the right override it is mapped.
    b2 = MapBuilder(ring, MarkerSizes(0.2, {42: 0.16}))
    for f in _frames(sim, scene.mapping_stations, 1):
        b2.add_frame(f)
    err = map_error(b2.build("paper"), scene.truth_map())
    assert err["n"] == len(scene.markers) and err["position_max_mm"] < 1e-3, err["per_marker"]


def test_candidates_contain_true_pose_of_far_face_on_marker(ring):
    """The refined IPPE pair contains the exact pose (OpenCV's IPPE alone misses it here)."""
    model = ring["cam0"].model
    T = geo.make_transform(np.diag([1.0, -1.0, -1.0]), [0.9, -0.3, 5.38])
    px = model.project(geo.transform_points(T, marker_corners(0.2)))
    cand = solve_marker_ippe_undistorted(model.normalize(px), 0.2, [model.fx, model.fy], mirror=True,
                                         min_separation=np.radians(1.0))
    poses, amb = cand.poses, cand.ambiguity
    dp, dr = geo.pose_distance(poses[0], T)
    assert dp < 1e-6 and dr < 1e-6, f"best candidate off by {dp:.2e} m, {np.degrees(dr):.3f} deg"
    assert amb < 0.01, f"ambiguity {amb}"


def _hall(n_markers: int, spacing: float = 0.8, station_step: float = 1.5) -> Scene:
    """A corridor 4 m wide, markers alternating on both walls, stations along the centre line."""
    from aruco_ring_localization.simulation.scene import Plate, Room

    length = (n_markers / 2) * spacing + 3.0
    markers = [SceneMarker(k, marker_pose([1.5 + (k // 2) * spacing + (spacing / 2 if k % 2 else 0.0),
                                           0.0 if k % 2 == 0 else 4.0, 1.0 + 0.3 * ((k // 2) % 3)],
                                          np.pi / 2 if k % 2 == 0 else -np.pi / 2), 0.2)
               for k in range(n_markers)]
    stations = [(x, 2.0, 0.0) for x in np.arange(1.5, length - 1.0, station_step)]
    return Scene(name="hall", world_frame="world", room=Room((0.0, 0.0), (length, 4.0), 3.0),
                 plate=Plate((length / 2, 2.0), (length - 1.0, 2.0)), markers=markers,
                 mapping_pose=stations[0], mapping_stations=stations)


def test_long_hall_with_miscalibrated_ring_does_not_drift(ring):
    """More stations than the init window: the growing initialisation's adjustments (extrinsics
    calibration, sliding window) run, and the final BA brings the map to the noise level."""
    from aruco_ring_localization.simulation.ring_sim import perturb_ring

    from aruco_ring_localization.mapping import MappingOptions

    scene = _hall(28)
    sim = RingSimulator(scene, perturb_ring(ring, seed=3), pixel_noise=0.3, seed=4, max_range=6.0)
    # A small hall and a small window keep the test fast; the code path is the one of long halls.
    b = MapBuilder(ring, MarkerSizes(0.2), options=MappingOptions(init_window_stations=4, init_calibrate_after=3,
                                                                   init_calibrate_max=6, init_ba_every=2))
    for s, pose in enumerate(scene.mapping_stations):
        b.add_frame(sim.observe(Scene.T_world_base(pose)), station=s)
    assert b.station_count > b.options.init_window_stations, b.station_count
    truth = scene.truth_map()
    paper = map_error(b.build("paper"), truth, best_fit=True)
    refined = map_error(b.build("refined"), truth, best_fit=True)
    assert refined["n"] == len(truth), f"mapped {refined['n']} of {len(truth)}"
    # 8 stations are too few to show the drift itself (17 mm with or without the adjustments; a
    # 40 m hall: 1 m without, 3 cm with, see bench_mapping): this checks the path runs and stays sane.
    assert paper["position_max_mm"] < 40.0, f"initialisation max error {paper['position_max_mm']:.1f} mm"
    assert refined["position_rms_mm"] < 3.0, f"refined RMS {refined['position_rms_mm']:.2f} mm"
    assert b.last_ba.rms_px_after < 0.4, f"BA RMS {b.last_ba.rms_px_after:.3f} px"


def test_station_linked_through_one_far_marker_does_not_reject_good_markers(ring, scene):
    """Issue 15: a driven mapping run with frames missing cameras had stations that saw one mapped
    marker and one more, both 5 m away, through one camera. Such a station's yaw comes from that one
    marker's single-view orientation (degrees off), which put the other marker 0.25 m off and got
    good markers rejected as "inconsistent between stations". Only well-linked stations testify now."""
    sim = RingSimulator(scene, ring, pixel_noise=0.3, seed=3)
    b = MapBuilder(ring, MarkerSizes(0.2))
    for f in _frames(sim, [scene.mapping_pose], 3):
        b.add_frame(f, station="centre")
    x0, y0, yaw0 = scene.mapping_pose
    weak = 0
    for dx in np.linspace(-1.5, 1.5, 7):
        for dy in np.linspace(-1.0, 1.0, 5):
            for dyaw in np.radians([0, 45, 90, 135, 180, 225, 270, 315]):
                f = sim.observe(Scene.T_world_base((x0 + dx, y0 + dy, yaw0 + dyaw)), stamp=1.0 + weak)
                for name, cf in f.cameras.items():
                    if sorted(o.marker_id for o in cf.observations) == [126, 777]:
                        b.add_frame(RingFrame(cf.stamp, {name: cf}), station=("weak", weak))
                        weak += 1
    assert weak > 50, f"only {weak} weak stations"
    assert b.rejected_markers() == {}, f"rejected {b.rejected_markers()}"
    m = b.build("paper")
    assert sorted(m.ids) == sorted(sm.marker_id for sm in scene.markers)


def test_misread_id_is_not_mapped_and_says_why(ring, scene):
    """A driven simulated run had ids that are not in the lab (445, 662) once or twice in 660 frames: a
    misread id flickers, a marker in view of a still robot is detected in nearly every frame."""
    sim = RingSimulator(scene, ring, pixel_noise=0.3, seed=4)
    frames = list(_frames(sim, [scene.mapping_pose], 10))
    cam = next(n for n, cf in frames[3].cameras.items() if cf.observations)
    real = frames[3].cameras[cam].observations[0]
    frames[3].cameras[cam].observations.append(MarkerObservation(999, real.corners[::-1] + 40.0))

    def build(**opts):
        from aruco_ring_localization.config import with_overrides
        from aruco_ring_localization.mapping import MappingOptions

        b = MapBuilder(ring, MarkerSizes(0.2), options=with_overrides(MappingOptions(), opts))
        for f in frames:
            b.add_frame(f)
        return b

    assert 999 in build().build("paper")  # off by default: a moving rig sees real tags as rarely
    b = build(min_detection_ratio=0.3)
    assert 999 in b.rejected_markers() and "misread" in b.rejected_markers()[999], b.rejected_markers()
    m = b.build("paper")
    assert sorted(m.ids) == sorted(sm.marker_id for sm in scene.markers)
    # What ~save_map and build-map say: loudly, with the reason.
    assert list(b.unmapped(m)) == [999]
    assert b.format_unmapped(m).startswith("WARNING: 1 of 11 detected markers are NOT in the map: 999: detected in")
    assert b.format_unmapped(build(min_detection_ratio=0.0).build("paper")) == ""
    assert 999 in build(min_detection_ratio=0.0).build("paper")


def _turning_free_running(sim, ring, pose, amplitude, frames, period=0.1):
    """Ring frames of a ring swinging on the spot (yaw0 + ``amplitude`` sin(t / 2), rad; a steady turn
    would only look like a constant error of each camera's yaw, which the extrinsics absorb) with
    free-running cameras: camera k exposed k/8 of a period after the frame's first, each from the
    pose at its own time."""
    x, y, yaw0 = pose
    n = len(ring.cameras)
    for i in range(frames):
        f = RingFrame(stamp=period * i)
        for k, cam in enumerate(ring.cameras):
            t = period * i + period * k / n
            T = Scene.T_world_base((x, y, yaw0 + amplitude * np.sin(0.5 * t)))
            f.cameras[cam.name] = CameraFrame(camera=cam.name, stamp=t, observations=sim.observe_camera(T, cam))
        yield f


@pytest.mark.parametrize("spread, worse", [(0.005, False), (-1.0, True)])
def test_free_running_cameras_of_a_turning_ring_map_by_exposure(ring, scene, spread, worse):
    """A turning ring's free-running cameras see it at 8 poses per ring frame: split into the parts
    exposed together (``max_stamp_spread``), the map is exact; one station pose for the whole ring
    frame (the old behaviour, a negative spread) bends it or refuses markers as inconsistent."""
    sim = RingSimulator(scene, ring, pixel_noise=0.0, seed=0)
    b = MapBuilder(ring, MarkerSizes(0.2), method="refined",
                   options=dataclasses.replace(MappingOptions(), max_stamp_spread=spread))
    for f in _turning_free_running(sim, ring, scene.mapping_pose, 1.0, 120):
        b.add_frame(f)
    err = map_error(b.build(), scene.truth_map(), best_fit=True)
    if worse:   # markers refused as inconsistent between stations, or the map bent
        assert err["n"] < len(scene.markers) or err["position_rms_mm"] > 5.0, \
            f"whole ring frames: {err['n']} markers, {err['position_rms_mm']:.2f} mm"
    else:
        assert err["n"] == len(scene.markers), f"mapped {err['n']} of {len(scene.markers)}: missing {err['missing']}"
        assert err["position_rms_mm"] < 0.5, f"ring frames split by exposure: {err['position_rms_mm']:.3f} mm"


def test_an_se3_station_testifies_only_with_markers_spanning_a_plane():
    """Two markers leave an SE(3) station free to turn about their line, three on a line too;
    three spanning a plane fix it (the spread check's witnesses, MapBuilder._check_spread)."""
    def at(*xyz):
        T = np.eye(4)
        T[:3, 3] = xyz
        return T
    assert not MapBuilder._spans_plane([at(0, 0, 0), at(1, 0, 0)])
    assert not MapBuilder._spans_plane([at(0, 0, 0), at(1, 0, 0), at(2, 0.001, 0)])
    assert MapBuilder._spans_plane([at(0, 0, 0), at(1, 0, 0), at(0, 0, 0.5)])
    assert MapBuilder._two_apart([at(0, 0, 0), at(1, 0, 0)])   # enough for a ground robot's planar station


def test_extrinsics_prior_from_the_ring_file(ring, scene):
    """``extrinsics_prior: ring``: each camera's prior is the ring file's extrinsics_std. A camera
    declared exact (std 0) stays at its calibration while the others are refined (their motion
    from the file is the adjustment's, the exact one's is none: the common motion is taken out
    weighted by the priors); ``options`` (the default) moves every camera; an unknown value is
    refused by name."""
    from aruco_ring_localization.errors import ConfigError
    from aruco_ring_localization.ring import CameraRing, RingCamera
    from aruco_ring_localization.simulation.ring_sim import perturb_ring

    true_ring = perturb_ring(ring, seed=1)
    sim = RingSimulator(scene, true_ring, pixel_noise=0.3, seed=2)
    frames = list(_frames(sim, scene.mapping_stations, 6))
    exact = ring.names[0]
    declared = CameraRing([RingCamera(c.name, c.frame_id, c.model, c.T_base_cam, c.namespace,
                                      tuple([0.0] * 6) if c.name == exact else c.extrinsics_std, c.wiggle)
                           for c in ring], ring.base_frame)

    def moved(options, r):
        b = MapBuilder(r, MarkerSizes(0.2), options=options)
        for f in frames:
            b.add_frame(f)
        m = b.build("refined")
        return {c: geo.pose_distance(r[c].T_base_cam, m.ring_extrinsics[c]) for c in r.names}

    ring_mode = moved(MappingOptions(extrinsics_prior="ring"), declared)
    default = moved(MappingOptions(), declared)
    assert ring_mode[exact][0] < 1e-5 and ring_mode[exact][1] < 1e-5, ring_mode[exact]
    assert default[exact][0] > 1e-4, f"the default moved camera {exact} by {default[exact]} only"
    others = [c for c in ring.names if c != exact]
    assert max(ring_mode[c][1] for c in others) > 1e-4, ring_mode
    with pytest.raises(ConfigError, match="extrinsics_prior"):
        MappingOptions(extrinsics_prior="file")
