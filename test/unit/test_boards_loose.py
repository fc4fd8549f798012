"""Loose boards: tags with a play about their layout (TagSLAM's tag_position_noise / tag_rotation_noise),
mapped each as its own unknown tied to a board frame by a relative-pose prior."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.boards import Board, BoardSet, grid_board, loose_priors
from aruco_ring_localization.bundle_adjustment import BAOptions, BAProblem, MarkerPriors, _Model, bundle_adjust
from aruco_ring_localization.errors import ConfigError, GeometryError
from aruco_ring_localization.importers import tagslam_boards
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.mapping import MapBuilder

from helpers import ba_dense_reference, ba_jacobian_rows, synthetic_ba_problem as _scene

DATA = Path(__file__).resolve().parents[1] / "data" / "tagslam"


def _relative(T_mk, pairs, pos_std=0.001, rot_std=0.002, seed=5):
    """Relative priors between the pairs, their poses a little off the truth (so the rows are not 0)."""
    rng = np.random.default_rng(seed)
    Z = []
    for a, b in pairs:
        off = geo.make_transform(geo.rotation_from_rvec(rng.normal(0, 0.01, 3)), rng.normal(0, 0.005, 3))
        Z.append(geo.inverse(T_mk[a]) @ T_mk[b] @ off)
    n = len(pairs)
    return MarkerPriors(relative_marker=np.array(pairs, dtype=int).reshape(-1, 2), relative_pose=np.array(Z),
                        relative_position_std=np.full(n, pos_std), relative_rotation_std=np.full(n, rot_std))


@pytest.mark.parametrize("fixed_marker", [None, 1])
def test_relative_pose_jacobian_matches_finite_differences(fixed_marker):
    """The relative-pose rows (a fixed marker's columns left out) against central differences."""
    prob, (T_mk, _, _) = _scene(seed=4, M=4, S=3, C=2, per=12)
    prob.priors = _relative(T_mk, [(0, 1), (0, 2), (3, 1), (2, 3)])
    if fixed_marker is not None:
        prob.fixed_station, prob.fixed_marker = None, fixed_marker
    model = _Model(prob, BAOptions())
    assert model._rel_coupled
    assert model.n_res - model.n_obs_res == 24
    J, Jn = ba_jacobian_rows(model, slice(model.n_obs_res, model.n_res))
    err = np.max(np.abs(J - Jn)) / np.max(np.abs(J))
    assert err < 1e-6, f"relative Jacobian error of the relative-pose rows {err:.2e}"
    assert np.count_nonzero(np.abs(Jn) > 1e-9) <= np.count_nonzero(J)


@pytest.mark.parametrize("case", ["markers", "stations"])
def test_coupled_solve_and_covariance_equal_dense(case):
    """Relative poses (and a distance) couple markers, one of them with no observation (a board
    frame): the damped step (markers or stations eliminated) equals a dense solve of J^T W J, and the
    markers' covariances equal the blocks of its inverse."""
    from aruco_ring_localization.bundle_adjustment import _marker_covariances

    if case == "stations":
        prob, (T_mk, _, _) = _scene(seed=3, M=3, S=12, C=2, per=120)
    else:
        prob, (T_mk, _, _) = _scene(seed=3, M=5, S=3, C=2, per=40)
    M = len(T_mk)
    frame = T_mk[0] @ geo.make_transform(np.eye(3), [0.1, 0.0, 0.0])
    prob.T_W_markers = np.concatenate([prob.T_W_markers, frame[None]])
    prob.sizes = np.concatenate([prob.sizes, [1.0]])
    T_all = np.concatenate([T_mk, frame[None]])
    pr = _relative(T_all, [(M, k) for k in range(M)])
    c0 = marker_corners(0.2)[0]
    prob.priors = MarkerPriors(relative_marker=pr.relative_marker, relative_pose=pr.relative_pose,
                               relative_position_std=pr.relative_position_std,
                               relative_rotation_std=pr.relative_rotation_std,
                               distance_marker=[[0, 1]], distance_point=[[c0, np.zeros(3)]], distance=[0.5],
                               distance_std=[1e-3])
    model = _Model(prob, BAOptions(refine_extrinsics=True))
    assert model._rel_coupled and model._station_elimination() == (case == "stations")
    ref = ba_dense_reference(model)
    H, H_ref = ref.H, ref.H_ref
    assert np.max(np.abs(H.toarray() - H_ref)) <= 1e-9 * np.max(np.abs(H_ref))
    assert np.max(np.abs(ref.dx - ref.dx_ref)) <= 1e-7 * np.max(np.abs(ref.dx_ref))
    cov, _ = _marker_covariances(model, H, 1.0)
    Hinv = np.linalg.inv(H_ref)
    for k in range(M + 1):
        c = model.col_m[k]
        ref = Hinv[c:c + 6, c:c + 6]
        assert np.max(np.abs(cov[k] - ref)) <= 1e-6 * np.max(np.abs(ref)), k


def _loose_scene(seed: int = 0, play: float = 0.002):
    """A 2 x 3 board whose tags sit ``play`` m (per axis, ~N(0, play)) and ~0.1 deg off their layout,
    seen by one camera from 8 stations (all six tags each), 0.1 px corner noise."""
    rng = np.random.default_rng(seed)
    board = grid_board("b", 0, rows=2, columns=3, size=0.12, spacing=0.25)
    T_W_b = geo.make_transform(geo.rotation_from_rvec([np.pi, 0.0, 0.0]), [-0.15, 0.075, 1.5])
    T_true = {}
    for m in board.ids:
        off = geo.make_transform(geo.rotation_from_rvec(rng.normal(0, np.radians(0.1), 3)), rng.normal(0, play, 3))
        T_true[m] = T_W_b @ board.layout[m] @ off
    stations = [geo.make_transform(geo.rotation_from_rvec([0.15 * np.cos(a), 0.15 * np.sin(a), 0.0]),
                                   [0.3 * np.sin(a), -0.3 * np.cos(a), 0.0])
                for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    stations[0] = np.eye(4)
    mids = board.ids
    om, os_, xy = [], [], []
    for s, T_s in enumerate(stations):
        for k, m in enumerate(mids):
            p = geo.transform_points(geo.inverse(T_s) @ T_true[m], marker_corners(0.12))
            om.append(k), os_.append(s)
            xy.append(p[:, :2] / p[:, 2:] + rng.normal(0, 0.1 / 800.0, (4, 2)))
    T_start = np.stack([T_W_b @ board.layout[m] for m in mids])      # the layout: off by the play
    n = len(om)
    prob = BAProblem(T_start, np.full(len(mids), 0.12), np.stack(stations), np.eye(4)[None], np.array(om),
                     np.array(os_), np.zeros(n, dtype=int), np.array(xy), np.full((n, 2), 800.0),
                     fixed_marker=None, fixed_station=0)
    return board, mids, T_true, prob


def test_a_loose_board_recovers_its_tags_off_the_layout_where_the_rigid_one_cannot():
    """Tags ~2 mm off their layout: the loose board (2 mm / 0.2 deg play) maps each where it is;
    the rigid board can only put them on the layout."""
    board, mids, T_true, prob = _loose_scene(seed=7)
    layout_err = [np.linalg.norm((prob.T_W_markers[k] @ geo.inverse(T_true[m]))[:3, 3]) for k, m in enumerate(mids)]
    opts = BAOptions(pixel_noise=0.1)
    loose = BoardSet([Board(board.name, board.layout, tag_position_std=0.002, tag_rotation_std_deg=0.2)])
    rigid = BoardSet([board])

    def errors(boards):
        res = MapBuilder._adjust(prob, mids, opts, boards)
        assert res.T_W_markers.shape == (len(mids), 4, 4) and res.marker_cov.shape == (len(mids), 6, 6)
        # compared after the best rigid fit of the centres (the gauge: station 0 only)
        P = np.array([res.T_W_markers[k][:3, 3] for k in range(len(mids))])
        Q = np.array([T_true[m][:3, 3] for m in mids])
        T = geo.rigid_fit(P, Q)
        return np.linalg.norm(P @ T[:3, :3].T + T[:3, 3] - Q, axis=1), res

    e_loose, res = errors(loose)
    e_rigid, _ = errors(rigid)
    assert np.sqrt(np.mean(np.square(layout_err))) > 0.002            # the scene's tags really are off
    assert np.sqrt(np.mean(e_rigid ** 2)) > 0.0015, e_rigid
    assert np.sqrt(np.mean(e_loose ** 2)) < 0.4 * np.sqrt(np.mean(e_rigid ** 2)), (e_loose, e_rigid)
    assert np.max(e_loose) < 0.001, e_loose
    assert np.all(np.linalg.eigvalsh(res.marker_cov) > 0)


def test_loose_priors_name_a_frame_per_board():
    b1 = Board("b1", grid_board("b1", 0, 1, 3, 0.1, 0.2).layout, tag_position_std=0.001, tag_rotation_std_deg=0.05)
    b2 = grid_board("b2", 10, 1, 2, 0.1, 0.2)
    boards = BoardSet([b1, b2])
    mids = [0, 2, 10, 11, 20]
    T = np.stack([geo.make_transform(np.eye(3), [0.12 * m, 0.0, 1.0]) for m in mids])
    frames, pairs, poses, pos, rot, of = loose_priors(mids, T, boards)
    assert len(frames) == 1 and list(of) == [0]
    assert pairs.tolist() == [[5, 0], [5, 1]]                      # frame after the 5 markers; markers 0 and 2
    np.testing.assert_allclose(poses[1], b1.layout[2])
    np.testing.assert_allclose(pos, 0.001) and np.testing.assert_allclose(rot, np.radians(0.05))
    assert boards.loose().boards == [b1] and boards.rigid().boards == [b2]
    with pytest.raises(GeometryError, match="both"):
        Board("x", b2.layout, tag_position_std=0.001)


def test_tagslam_boards_read_the_play(tmp_path):
    boards = tagslam_boards(str(DATA / "test_13" / "tagslam.yaml"), rig_bodies=("rig",))
    loose = [b for b in boards.boards if b.loose]
    assert len(loose) == len(boards) == 16
    b24 = boards.boards[boards.board_of(24)]
    assert b24.tag_position_std == pytest.approx(1e-4) and b24.tag_rotation_std_deg == pytest.approx(np.degrees(1e-4))
    b12 = boards.boards[boards.board_of(12)]
    assert b12.tag_position_std == pytest.approx(1e-3) and b12.tag_rotation_std_deg == pytest.approx(np.degrees(1e-3))
    exact = tagslam_boards(str(DATA / "test_13" / "tagslam.yaml"), rig_bodies=("rig",), play=False)
    assert not any(b.loose for b in exact.boards)
    p = tmp_path / "tagslam.yaml"
    p.write_text("bodies:\n - b:\n     is_static: true\n     type: board\n     default_tag_size: 0.1\n"
                 "     board: {tag_start_id: 0, tag_size: 0.1, tag_spacing: 0.2, tag_rows: 2, tag_columns: 2,\n"
                 "             tag_position_noise: -1, tag_rotation_noise: 0.001}\n")
    with pytest.raises(ConfigError) as err:
        tagslam_boards(str(p))
    assert err.value.key == "bodies[0].b.board.tag_position_noise"


def test_loose_and_rigid_boards_in_one_adjustment():
    """A loose board beside a rigid one (both off their layouts): the loose board's tags are mapped
    where they are, the rigid board's exactly on its layout (their relative poses the layout's)."""
    board, mids, T_true, prob = _loose_scene(seed=3)
    # split the 2 x 3 grid: tags 0-2 a loose board, 3-5 a rigid one (same layout poses)
    loose = Board("l", {m: board.layout[m] for m in (0, 1, 2)}, tag_position_std=0.002, tag_rotation_std_deg=0.2)
    rigid = Board("r", {m: board.layout[m] for m in (3, 4, 5)})
    res = MapBuilder._adjust(prob, mids, BAOptions(pixel_noise=0.1), BoardSet([loose, rigid]))
    assert res.T_W_markers.shape == (6, 4, 4) and res.marker_cov.shape == (6, 6, 6)
    T = res.T_W_markers
    for a, b in ((3, 4), (3, 5)):
        rel = geo.inverse(T[a]) @ T[b]
        np.testing.assert_allclose(rel, geo.inverse(board.layout[a]) @ board.layout[b], atol=1e-9)
    # the loose tags' centres follow the truth, not the layout (the truth is ~2 mm off it): after
    # the best rigid fit of the three centres to the true ones
    def fit_rms(P):
        Q = np.array([T_true[m][:3, 3] for m in (0, 1, 2)])
        F = geo.rigid_fit(P, Q)
        return float(np.sqrt(np.mean(np.sum((P @ F[:3, :3].T + F[:3, 3] - Q) ** 2, axis=1))))

    got = fit_rms(np.array([T[m][:3, 3] for m in (0, 1, 2)]))
    lay = fit_rms(np.array([board.layout[m][:3, 3] for m in (0, 1, 2)]))
    assert lay > 0.0005 and got < 0.3 * lay, (got, lay)
