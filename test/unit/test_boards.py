"""Rigid boards of markers: layouts, TagSLAM's board bodies, the board as one unknown of the adjustment."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.boards import (Board, BoardSet, collapse, expand_covariances, expand_poses,
                                            fit_board_pose, grid_board, solve_board_view)
from aruco_ring_localization.bundle_adjustment import BAOptions, BAProblem, bundle_adjust
from aruco_ring_localization.errors import ConfigError, GeometryError
from aruco_ring_localization.importers import read_tagslam_tags, tagslam_boards
from aruco_ring_localization.markers import marker_corners

NOISE = 0.05   # px: the tolerances below are of this noise (a planar scene from one camera: weak depth)
DATA = Path(__file__).resolve().parents[1] / "data" / "tagslam"


def test_grid_and_staggered_layouts():
    b = grid_board("b", 6, rows=2, columns=3, size=0.12, spacing=0.25)
    assert b.ids == list(range(6, 12))
    np.testing.assert_allclose(b.layout[7][:3, 3], [0.15, 0.0, 0.0])       # 0.12 * 1.25 apart, along x
    np.testing.assert_allclose(b.layout[9][:3, 3], [0.0, 0.15, 0.0])       # the second row up (+y)
    s = grid_board("s", 72, rows=7, columns=5, size=0.05, spacing=1.0, staggered=True)
    assert s.ids == list(range(72, 90))                                    # 4 rows of 3, 3 rows of 2
    np.testing.assert_allclose(s.layout[74][:3, 3], [0.4, 0.0, 0.0])       # row 0: columns 0, 2, 4
    np.testing.assert_allclose(s.layout[75][:3, 3], [0.1, -0.1, 0.0])      # row 1 starts at column 1, down (-y)
    for T in s.layout.values():
        np.testing.assert_allclose(T[:3, :3], np.eye(3))
    with pytest.raises(GeometryError):
        grid_board("bad", 0, rows=0, columns=3, size=0.1, spacing=0.2)
    with pytest.raises(GeometryError, match="marker 7"):
        BoardSet([b, grid_board("c", 7, 1, 1, 0.1, 0.0)])


def test_tagslam_boards_of_test_24():
    boards = tagslam_boards(str(DATA / "test_24" / "tagslam.yaml"), rig_bodies=("rig",))
    assert len(boards) == 12
    b144 = boards.boards[boards.board_of(144)]
    assert b144.name == "rect_board_144" and b144.ids == list(range(144, 162))
    assert boards.board_of(161) == boards.board_of(144) and boards.board_of(162) is None
    assert boards.boards[boards.board_of(2080)].ids == list(range(2080, 2085))     # 3 x 3 staggered: 5 tags
    # the sizes follow the staggered layout (18 tags per 7 x 5 board, not 35)
    t24 = read_tagslam_tags(str(DATA / "test_24" / "tagslam.yaml"))
    assert 90 not in t24.sizes and 89 in t24.sizes


def test_tagslam_board_without_spacing_names_the_key(tmp_path):
    p = tmp_path / "tagslam.yaml"
    p.write_text("bodies:\n - b:\n     is_static: true\n     type: board\n     default_tag_size: 0.1\n"
                 "     board: {tag_start_id: 0, tag_size: 0.1, tag_rows: 2, tag_columns: 2}\n")
    with pytest.raises(ConfigError) as err:
        tagslam_boards(str(p))
    assert err.value.key == "bodies[0].b.board.tag_spacing"


def _board_scene(seed: int = 0):
    rng = np.random.default_rng(seed)
    board = grid_board("b", 0, rows=2, columns=3, size=0.12, spacing=0.25)
    T_W_b = geo.make_transform(geo.rotation_from_rvec([np.pi, 0.1, 0.05]), [-0.2, -0.1, 3.0])
    return rng, board, T_W_b


def test_board_pose_from_its_markers_outvotes_a_mirrored_one():
    rng, board, T_W_b = _board_scene()
    T_W = {m: T_W_b @ board.layout[m] for m in board.ids[:5]}
    # marker 1 mirrored (its orientation tilted 40 deg about its own centre), marker 4 moved 10 cm
    T_W[1] = T_W[1] @ geo.make_transform(geo.rotation_from_rvec([0.7, 0, 0]), [0, 0, 0])
    T_W[4] = geo.make_transform(np.eye(3), [0.1, 0, 0]) @ T_W[4]
    T, agree = fit_board_pose(board, T_W)
    assert sorted(agree) == [0, 1, 2, 3]         # the centres: the mirrored orientation does not matter
    dp, da = geo.pose_distance(T, T_W_b)
    assert dp < 1e-9 and da < 1e-9
    # two markers only: the vote over their poses (the mirrored one loses on weight)
    T2, agree2 = fit_board_pose(board, {0: T_W[0], 1: T_W[1]}, weights={0: 5.0, 1: 1.0})
    assert agree2 == [0] and geo.pose_distance(T2, T_W_b)[1] < 1e-9


def test_board_view_resolves_each_markers_ambiguity():
    rng, board, T_c_b = _board_scene(1)
    focal = np.array([800.0, 800.0])
    views = []
    for m in board.ids:
        T = T_c_b @ board.layout[m]
        p = geo.transform_points(T, marker_corners(0.12))
        xy = p[:, :2] / p[:, 2:] + rng.normal(0, 0.05 / 800.0, (4, 2))
        wrong = T @ geo.make_transform(geo.rotation_from_rvec([0.5, 0.0, 0.0]), [0, 0, 0])
        views.append((m, xy, 0.12, [wrong, T] if m != 2 else [T, wrong]))   # mostly the mirror first
    T, rms, per = solve_board_view(board, views, focal)
    dp, da = geo.pose_distance(T, T_c_b)
    assert dp < 0.005 and np.degrees(da) < 0.5
    assert rms < 0.1 and max(per.values()) < 0.15                      # the mirror would be 29 deg off


def test_a_board_is_one_unknown_of_the_adjustment_and_places_its_unseen_marker():
    """Stations see markers 0-3 of a 6-marker board (and a loose marker 10); started 3 cm / 2 deg off,
    the collapsed adjustment recovers every marker, 4 and 5 (never seen) from the layout."""
    rng, board, T_W_b = _board_scene(2)
    boards = BoardSet([board])
    T_true = {m: T_W_b @ board.layout[m] for m in board.ids}
    T_true[10] = geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]), [0.6, 0.2, 3.2])
    stations = [geo.make_transform(geo.rotation_from_rvec([0, 0.08 * s, 0]), [0.25 * s - 0.4, 0.05 * s, 0.1 * s])
                for s in range(5)]
    seen = [0, 1, 2, 3, 10]
    om, os_, xy = [], [], []
    for s, T_s in enumerate(stations):
        for m in seen:
            p = geo.transform_points(geo.inverse(T_s) @ T_true[m], marker_corners(0.12))
            om.append(m), os_.append(s)
            xy.append(p[:, :2] / p[:, 2:] + rng.normal(0, NOISE / 800.0, (4, 2)))
    mids = sorted(T_true)                                       # 0..5 and 10
    mi = {m: k for k, m in enumerate(mids)}
    off = geo.make_transform(geo.rotation_from_rvec([0.0, 0.035, 0.0]), [0.03, -0.02, 0.01])
    T_start = np.stack([off @ T_true[m] for m in mids])
    n = len(om)
    prob = BAProblem(T_start, np.full(len(mids), 0.12), np.stack(stations), np.eye(4)[None],
                     np.array([mi[m] for m in om]), np.array(os_), np.zeros(n, dtype=int), np.array(xy),
                     np.full((n, 2), 800.0), fixed_marker=None, fixed_station=0)
    T_u, sizes_u, X, c = collapse(mids, prob.T_W_markers, prob.sizes, prob.obs_marker, boards)
    assert c.n_units == 2                                       # the board and marker 10
    sub = BAProblem(T_u, sizes_u, prob.T_W_stations, prob.T_base_cams, c.unit[prob.obs_marker], prob.obs_station,
                    prob.obs_camera, prob.obs_xy, prob.obs_focal, fixed_marker=None, fixed_station=0, obs_object=X)
    res = bundle_adjust(sub, BAOptions(pixel_noise=NOISE))
    T_m = expand_poses(res.T_W_markers, c)
    for k, m in enumerate(mids):
        dp, da = geo.pose_distance(T_m[k], T_true[m])
        assert dp < 0.003 and np.degrees(da) < 0.2, (m, dp, np.degrees(da))
    cov = expand_covariances(res.marker_cov, res.T_W_markers, c)
    # marker 0 is the board's origin: the board's covariance; marker 5 (unseen) gets it moved along the layout
    np.testing.assert_allclose(cov[mi[0]], res.marker_cov[c.unit[mi[0]]])
    a = res.T_W_markers[c.unit[mi[5]]][:3, :3] @ board.layout[5][:3, 3]
    J = np.eye(6)
    J[3:, :3] = -geo.skew(a)
    np.testing.assert_allclose(cov[mi[5]], J @ res.marker_cov[c.unit[mi[5]]] @ J.T)
    assert np.all(np.linalg.eigvalsh(cov[mi[5]]) > 0)
    # without the board, markers 4 and 5 have no observation: the same adjustment cannot place them
    assert res.rms_px_after < 0.5


def test_mapbuilder_places_a_boards_markers(monkeypatch):
    """The builder's board step: markers of a board it mapped are placed by the layout, the ones it
    did not map (rejected or never seen) included, and the rejection is lifted."""
    from aruco_ring_localization.mapping import MapBuilder, _Init
    _, board, T_W_b = _board_scene(3)
    b = MapBuilder.__new__(MapBuilder)
    b._obs = []
    init = _Init(reference=0, ref_station=0, T_W_markers={m: T_W_b @ board.layout[m] for m in (0, 1, 2)},
                 T_W_stations={0: np.eye(4)}, marker_obs={0: [0], 1: [0], 2: [0]}, unlinked=[4],
                 rejected={3: "inconsistent"})
    out = b._place_boards(init, BoardSet([board]))
    assert sorted(out.T_W_markers) == board.ids and 3 not in out.rejected and out.unlinked == []
    for m in board.ids:
        assert geo.pose_distance(out.T_W_markers[m], T_W_b @ board.layout[m])[0] < 1e-9


def test_build_map_boards_option_reaches_the_mapper(tmp_path):
    """``build-map --boards tagslam.yaml`` -> ``map/boards_file`` -> the pipeline's MapBuilder; a file
    without boards is refused by name."""
    import argparse

    from aruco_ring_localization.cli import build_map
    from aruco_ring_localization.config import with_overrides
    from aruco_ring_localization.pipeline import MappingPipeline
    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.schemas import MapperConfig
    from helpers import RING_YAML

    parser = argparse.ArgumentParser()
    build_map.add_arguments(parser)
    path = str(DATA / "test_24" / "tagslam.yaml")
    config = build_map.load_config(parser.parse_args(["x.bag", "--out", "m.yaml", "--boards", path]))
    assert config.map.boards_file == path
    ring = CameraRing.load(str(RING_YAML))
    offline = {"input.use_tf": False, "input.camera_info_fallback": True}
    pipe = MappingPipeline(with_overrides(config, offline), ring)
    assert pipe.builder.boards is not None and len(pipe.builder.boards) == 12
    empty = tmp_path / "tagslam.yaml"
    empty.write_text("bodies:\n - lab:\n     is_static: true\n     default_tag_size: 0.1\n")
    with pytest.raises(ConfigError) as err:
        MappingPipeline(with_overrides(MapperConfig(), {**offline, "map.boards_file": str(empty)}), ring)
    assert err.value.key == "bodies"


def test_grazing_and_small_views_are_dropped_only_when_asked():
    """TagSLAM's minimum_viewing_angle / minimum_tag_area as mapping options (off by default)."""
    from aruco_ring_localization.camera import CameraModel  # noqa: F401  (the ring's model projects)
    from aruco_ring_localization.detections import CameraFrame, MarkerObservation, RingFrame
    from aruco_ring_localization.mapping import MapBuilder, MappingOptions, _area_px, _viewing_angle
    from aruco_ring_localization.markers import MarkerSizes
    from aruco_ring_localization.ring import CameraRing
    from helpers import RING_YAML

    assert _area_px(np.array([[0, 0], [10, 0], [10, 20], [0, 20]])) == pytest.approx(200.0)
    face_on = geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]), [0.0, 0.0, 2.0])
    assert np.degrees(_viewing_angle(face_on)) == pytest.approx(90.0)
    tilted = face_on @ geo.make_transform(geo.rotation_from_rvec([0, np.radians(80), 0]), [0, 0, 0])
    assert np.degrees(_viewing_angle(tilted)) == pytest.approx(10.0, abs=1e-6)
    # its mirror about the line of sight meets it at the same angle
    ring = CameraRing.load(str(RING_YAML))
    cam = ring[ring.names[0]]
    poses = {1: face_on, 2: geo.make_transform(np.eye(3), [0.6, 0, 0]) @ tilted,
             3: geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]), [-0.5, 0.0, 6.0])}
    obs = [MarkerObservation(i, cam.model.project(geo.transform_points(T, marker_corners(0.2))))
           for i, T in poses.items()]
    areas = {o.marker_id: _area_px(o.corners) for o in obs}
    assert areas[3] < areas[1] and areas[2] < areas[1]
    frame = RingFrame(0.0, {cam.name: CameraFrame(cam.name, 0.0, obs)})
    for opts, kept in ((MappingOptions(), {1, 2, 3}), (MappingOptions(min_viewing_angle_deg=12.0), {1, 3}),
                       (MappingOptions(min_marker_area_px=0.9 * areas[1]), {1})):
        b = MapBuilder(ring, MarkerSizes(0.2), method="paper", options=opts)
        b.add_frame(frame)
        assert {o.marker_id for o in b._obs} == kept
