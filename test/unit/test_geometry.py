"""Unit tests of geometry.py: SE(3)/SE(2) round trips, angle arithmetic, rotation averaging, validation.

Property tests use Hypothesis with derandomized generation (fixed examples every run) and a
modest number of examples; the rest uses seeded numpy generators.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import GeometryError

from helpers import assert_close, axis_angle_matrix, random_rotation, random_transform

PROPS = settings(max_examples=100, derandomize=True, deadline=None)

coord = st.floats(-1.0, 1.0, allow_nan=False)
quat_raw = st.tuples(coord, coord, coord, coord).filter(lambda q: np.linalg.norm(q) > 0.1)
trans = st.tuples(*[st.floats(-20.0, 20.0, allow_nan=False)] * 3)
angle = st.floats(-math.pi, math.pi, allow_nan=False)
any_angle = st.floats(-1e3, 1e3, allow_nan=False)


def _unit(q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q)


@st.composite
def transforms(draw):
    T = np.eye(4)
    T[:3, :3] = geo.matrix_from_quaternion(_unit(draw(quat_raw)))
    T[:3, 3] = draw(trans)
    return T


# --- SE(3) basics ------------------------------------------------------------------------------

@PROPS
@given(transforms())
def test_inverse_times_transform_is_identity(T):
    assert_close(geo.inverse(T) @ T, np.eye(4), 1e-12, "inverse(T) @ T")
    assert_close(T @ geo.inverse(T), np.eye(4), 1e-12, "T @ inverse(T)")


@PROPS
@given(transforms())
def test_inverse_matches_numpy_inverse(T):
    assert_close(geo.inverse(T), np.linalg.inv(T), 1e-9, "inverse vs np.linalg.inv")


@PROPS
@given(transforms(), transforms(), transforms())
def test_compose_is_associative_and_matches_matmul(A, B, C):
    left = geo.compose(geo.compose(A, B), C)
    right = geo.compose(A, geo.compose(B, C))
    assert_close(left, right, 1e-10, "(AB)C vs A(BC)")
    assert_close(geo.compose(A, B, C), A @ B @ C, 1e-10, "compose(A, B, C) vs A @ B @ C")


def test_compose_of_nothing_is_identity_and_inverse_chains():
    rng = np.random.default_rng(1)
    T_a_b, T_b_c = random_transform(rng), random_transform(rng)
    T_a_c = geo.compose(T_a_b, T_b_c)
    assert_close(geo.compose(), np.eye(4), 0.0, "compose()")
    # inverse(T_a_c) = T_c_a = T_c_b T_b_a
    assert_close(geo.inverse(T_a_c), geo.compose(geo.inverse(T_b_c), geo.inverse(T_a_b)), 1e-10, "T_c_a")


def test_transform_points_applies_rotation_then_translation():
    rng = np.random.default_rng(2)
    T = random_transform(rng)
    pts = rng.normal(size=(7, 3))
    expected = (T @ np.c_[pts, np.ones(7)].T).T[:, :3]
    assert_close(geo.transform_points(T, pts), expected, 1e-12, "transform_points")
    # Round trip through the inverse.
    assert_close(geo.transform_points(geo.inverse(T), geo.transform_points(T, pts)), pts, 1e-10, "back")


def test_make_transform_defaults_and_values():
    assert_close(geo.make_transform(), np.eye(4), 0.0, "make_transform()")
    R = axis_angle_matrix([0, 0, 1], 0.3)
    T = geo.make_transform(R, [1, 2, 3])
    assert_close(T[:3, :3], R, 0.0, "R block")
    assert_close(T[:3, 3], [1, 2, 3], 0.0, "t block")
    assert_close(T[3], [0, 0, 0, 1], 0.0, "last row")


# --- rvec / tvec -------------------------------------------------------------------------------

@PROPS
@given(transforms())
def test_rvec_tvec_round_trip(T):
    rvec, tvec = geo.rvec_tvec_from_transform(T)
    assert rvec.shape == (3,) and tvec.shape == (3,)
    assert np.linalg.norm(rvec) <= math.pi + 1e-12, f"rvec angle {np.linalg.norm(rvec)} above pi"
    assert_close(geo.transform_from_rvec_tvec(rvec, tvec), T, 1e-10, "rvec/tvec round trip")


@PROPS
@given(transforms())
def test_rvec_agrees_with_opencv_rodrigues(T):
    rvec, _ = geo.rvec_tvec_from_transform(T)
    R_cv, _ = cv2.Rodrigues(rvec.reshape(3, 1))
    assert_close(geo.rotation_from_rvec(rvec), R_cv, 1e-10, "rotation_from_rvec vs cv2.Rodrigues")
    # At pi the rvec's sign is a free choice; below 1e-5 rad OpenCV rounds the rvec to zero.
    assume(1e-4 < geo.rotation_angle(T) < math.pi - 1e-3)
    rvec_cv, _ = cv2.Rodrigues(T[:3, :3])
    assert_close(rvec, rvec_cv.ravel(), 1e-7, "rvec_from_rotation vs cv2.Rodrigues")


@pytest.mark.parametrize("theta", [0.0, 1e-14, 1e-9, 1e-4, 1.0, math.pi - 1e-7, math.pi])
def test_rvec_round_trip_at_small_and_half_turn_angles(theta):
    rng = np.random.default_rng(3)
    for _ in range(5):
        axis = rng.normal(size=3)
        R = axis_angle_matrix(axis, theta)
        rvec = geo.rvec_from_rotation(R)
        assert abs(np.linalg.norm(rvec) - theta) < 1e-7, f"|rvec| = {np.linalg.norm(rvec)} for angle {theta}"
        assert_close(geo.rotation_from_rvec(rvec), R, 1e-9, f"round trip at angle {theta}")


def test_rvec_tvec_accept_opencv_column_vectors():
    T = geo.transform_from_rvec_tvec(np.array([[0.0], [0.0], [math.pi / 2]]), np.array([[1.0], [2.0], [3.0]]))
    assert_close(T[:3, :3], axis_angle_matrix([0, 0, 1], math.pi / 2), 1e-12, "rotation from (3,1) rvec")
    assert_close(T[:3, 3], [1, 2, 3], 0.0, "translation from (3,1) tvec")


def test_rvec_conversions_equal_the_rodrigues_formula_on_seeded_draws():
    # SciPy's Rotation replaced a hand-written Rodrigues formula: same matrices, and the inverse.
    rng = np.random.default_rng(13)
    for _ in range(200):
        axis, theta = rng.normal(size=3), rng.uniform(0.0, math.pi - 1e-3)
        rvec = axis / np.linalg.norm(axis) * theta
        R = axis_angle_matrix(axis, theta)
        assert_close(geo.rotation_from_rvec(rvec), R, 1e-12, "rotation_from_rvec vs Rodrigues")
        assert_close(geo.rvec_from_rotation(R), rvec, 1e-9, "rvec_from_rotation vs the drawn rvec")


@PROPS
@given(st.tuples(coord, coord, coord), st.tuples(coord, coord, coord))
def test_skew_is_the_cross_product(a, b):
    a, b = np.array(a), np.array(b)
    assert_close(geo.skew(a) @ b, np.cross(a, b), 1e-15, "skew(a) @ b vs cross(a, b)")
    assert_close(geo.skew(a), -geo.skew(a).T, 0.0, "skew is antisymmetric")
    stacked = geo.skew(np.stack([a, b]))
    assert stacked.shape == (2, 3, 3)
    assert_close(stacked[1], geo.skew(b), 0.0, "vectorised skew")


@pytest.mark.parametrize("theta", [0.0, 1e-7, 1e-3, 0.5, 2.0, 3.0])
def test_left_jacobian_matches_finite_differences(theta):
    # exp(w + d) ~ exp(J_l(w) d) exp(w): compare J_l against central differences of log(exp(w+d) exp(w)^T).
    rng = np.random.default_rng(14)
    axis = rng.normal(size=3)
    w = axis / np.linalg.norm(axis) * theta
    J = geo.so3_left_jacobian(w[None])[0]
    eps = 1e-6
    R0T = geo.rotation_from_rvec(w).T
    num = np.stack([(geo.rvec_from_rotation(geo.rotation_from_rvec(w + eps * e) @ R0T)
                     - geo.rvec_from_rotation(geo.rotation_from_rvec(w - eps * e) @ R0T)) / (2 * eps)
                    for e in np.eye(3)], axis=1)
    assert_close(J, num, 1e-8, f"left Jacobian at angle {theta}")


# --- quaternions -------------------------------------------------------------------------------

@PROPS
@given(quat_raw)
def test_quaternion_round_trip_up_to_sign(q):
    q = _unit(q)
    R = geo.matrix_from_quaternion(q)
    assert_close(R.T @ R, np.eye(3), 1e-12, "R^T R")
    assert np.linalg.det(R) > 0.999
    q2 = geo.quaternion_from_matrix(R)
    assert q2[3] >= 0.0, f"w = {q2[3]} < 0"
    assert abs(np.linalg.norm(q2) - 1.0) < 1e-12
    err = min(np.abs(q2 - q).max(), np.abs(q2 + q).max())
    assert err < 1e-9, f"quaternion round trip error {err:.2e}: {q} -> {q2}"
    # The 4x4 form gives the same quaternion.
    T = np.eye(4)
    T[:3, :3] = R
    assert_close(geo.quaternion_from_matrix(T), q2, 0.0, "from 4x4")


@PROPS
@given(quat_raw)
def test_negated_quaternion_is_the_same_rotation(q):
    q = _unit(q)
    assert_close(geo.matrix_from_quaternion(q), geo.matrix_from_quaternion(-q), 1e-15, "R(q) vs R(-q)")


@pytest.mark.parametrize("w", [0.0, 1e-12, -1e-12, 1e-6, -1e-6, -0.3, -1.0])
def test_quaternion_round_trip_near_half_turn_and_negative_w(w):
    rng = np.random.default_rng(4)
    for _ in range(20):
        v = rng.normal(size=3)
        v *= math.sqrt(1.0 - w * w) / np.linalg.norm(v)
        q = np.r_[v, w]
        q2 = geo.quaternion_from_matrix(geo.matrix_from_quaternion(q))
        err = min(np.abs(q2 - q).max(), np.abs(q2 + q).max())
        assert err < 1e-9, f"w={w}: round trip error {err:.2e}: {q} -> {q2}"
        assert q2[3] >= 0.0


def test_quaternion_of_known_rotations():
    q = geo.quaternion_from_matrix(axis_angle_matrix([0, 0, 1], math.pi / 2))
    assert_close(q, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], 1e-12, "90 deg about z")
    q = geo.quaternion_from_matrix(np.diag([1.0, -1.0, -1.0]))
    assert_close(np.abs(q), [1, 0, 0, 0], 1e-12, "180 deg about x")
    # The ring's cam0 optical frame: z forward = base +x, x right = base -y, y down = base -z.
    R = geo.matrix_from_quaternion([-0.5, 0.5, -0.5, 0.5])
    assert_close(R, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], 1e-12, "optical frame rotation")


def test_transform_from_translation_quaternion_and_slightly_unnormalised_quaternion():
    T = geo.transform_from_translation_quaternion([1, 2, 3], [0, 0, 0.7071, 0.7071])
    assert_close(T[:3, :3], axis_angle_matrix([0, 0, 1], math.pi / 2), 1e-12, "renormalised rotation")
    assert_close(T[:3, 3], [1, 2, 3], 0.0, "translation")


# --- roll / pitch / yaw -------------------------------------------------------------------------

@PROPS
@given(angle, st.floats(-math.pi / 2 + 1e-6, math.pi / 2 - 1e-6), angle)
def test_rpy_round_trip(roll, pitch, yaw):
    R = geo.matrix_from_rpy(roll, pitch, yaw)
    r2, p2, y2 = geo.rpy_from_matrix(R)
    # Angles are recovered modulo 2 pi; the matrix must be recovered to the bit.
    assert abs(geo.angle_diff(r2, roll)) < 1e-8 and abs(p2 - pitch) < 1e-9 and abs(geo.angle_diff(y2, yaw)) < 1e-8, \
        f"rpy ({roll}, {pitch}, {yaw}) -> ({r2}, {p2}, {y2})"
    assert_close(geo.matrix_from_rpy(r2, p2, y2), R, 1e-10, "matrix from recovered rpy")


def test_rpy_matches_fixed_axis_convention():
    roll, pitch, yaw = 0.1, -0.2, 0.3
    Rx = axis_angle_matrix([1, 0, 0], roll)
    Ry = axis_angle_matrix([0, 1, 0], pitch)
    Rz = axis_angle_matrix([0, 0, 1], yaw)
    assert_close(geo.matrix_from_rpy(roll, pitch, yaw), Rz @ Ry @ Rx, 1e-12, "R = Rz Ry Rx")


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2, math.pi / 2 - 1e-10, -math.pi / 2 + 1e-10,
                                   math.pi / 2 - 1e-7])
def test_rpy_at_gimbal_lock_reproduces_the_matrix(pitch):
    rng = np.random.default_rng(5)
    for _ in range(20):
        roll, yaw = rng.uniform(-math.pi, math.pi, size=2)
        R = geo.matrix_from_rpy(roll, pitch, yaw)
        r2, p2, y2 = geo.rpy_from_matrix(R)
        assert all(np.isfinite([r2, p2, y2]))
        assert abs(p2 - pitch) < 1e-6, f"pitch {pitch} -> {p2}"
        assert_close(geo.matrix_from_rpy(r2, p2, y2), R, 1e-7, f"gimbal lock at pitch {pitch}")


def test_rpy_from_4x4_uses_rotation_block():
    T = geo.make_transform(geo.matrix_from_rpy(0.1, 0.2, 0.3), [5, 6, 7])
    assert_close(geo.rpy_from_matrix(T), [0.1, 0.2, 0.3], 1e-12, "rpy of 4x4")


# --- SE(2) and angles -------------------------------------------------------------------------

@PROPS
@given(st.floats(-50, 50), st.floats(-50, 50), any_angle, st.floats(-2, 2))
def test_se2_round_trip(x, y, yaw, z):
    T = geo.transform_from_se2(x, y, yaw, z)
    geo.validate_transform(T)
    assert T[2, 3] == z
    x2, y2, yaw2 = geo.se2_from_transform(T)
    assert x2 == x and y2 == y
    assert abs(geo.angle_diff(yaw2, yaw)) < 1e-9, f"yaw {yaw} -> {yaw2}"
    assert -math.pi <= yaw2 <= math.pi


def test_se2_yaw_of_slightly_tilted_pose_is_the_heading():
    yaw = 2.5
    T = geo.make_transform(geo.matrix_from_rpy(0.02, -0.03, yaw), [1.0, -2.0, 0.1])
    x, y, yaw2 = geo.se2_from_transform(T)
    assert (x, y) == (1.0, -2.0)
    assert abs(geo.angle_diff(yaw2, yaw)) < 1e-12, f"heading {yaw2} vs yaw {yaw}"


@PROPS
@given(any_angle)
def test_wrap_angle_range_and_identity_on_the_circle(a):
    w = geo.wrap_angle(a)
    assert isinstance(w, float)
    assert -math.pi <= w < math.pi, f"wrap_angle({a!r}) = {w!r} outside [-pi, pi)"
    assert abs(math.sin(w) - math.sin(a)) < 1e-9 and abs(math.cos(w) - math.cos(a)) < 1e-9


@PROPS
@given(angle, st.integers(-20, 20))
def test_wrap_angle_is_2pi_periodic(a, k):
    w1, w2 = geo.wrap_angle(a), geo.wrap_angle(a + 2 * math.pi * k)
    # Near the cut at -pi the two may land on opposite ends of the range.
    assert abs(geo.wrap_angle(w1 - w2)) < 1e-9 or abs(abs(w1 - w2) - 2 * math.pi) < 1e-9, \
        f"wrap({a}) = {w1}, wrap({a} + 2pi*{k}) = {w2}"


@pytest.mark.parametrize("a", [math.pi, -math.pi, np.nextafter(-math.pi, -np.inf), np.nextafter(math.pi, np.inf),
                               np.nextafter(math.pi, 0.0), 3 * math.pi, -3 * math.pi, -1e-300, 0.0, 1e-300])
def test_wrap_angle_boundaries_stay_in_half_open_range(a):
    w = geo.wrap_angle(a)
    assert -math.pi <= w < math.pi, f"wrap_angle({a!r}) = {w!r} outside [-pi, pi)"
    arr = geo.wrap_angle(np.array([a, a]))
    assert np.all((arr >= -math.pi) & (arr < math.pi)), f"array wrap_angle({a!r}) = {arr!r}"


def test_wrap_angle_of_arrays():
    a = np.linspace(-20, 20, 1001)
    w = geo.wrap_angle(a)
    assert w.shape == a.shape
    assert np.all((w >= -math.pi) & (w < math.pi))
    assert_close(np.sin(w), np.sin(a), 1e-12, "sin")
    assert_close(np.cos(w), np.cos(a), 1e-12, "cos")


def test_angle_diff_across_the_cut():
    d = geo.angle_diff(math.radians(-179), math.radians(179))
    assert abs(d - math.radians(2)) < 1e-12, f"angle_diff(-179, 179) = {math.degrees(d)} deg, expected 2"
    d = geo.angle_diff(math.radians(179), math.radians(-179))
    assert abs(d + math.radians(2)) < 1e-12, f"angle_diff(179, -179) = {math.degrees(d)} deg, expected -2"
    arr = geo.angle_diff(np.radians([-179.0, 10.0]), np.radians([179.0, 350.0]))
    assert_close(np.degrees(arr), [2.0, 20.0], 1e-9, "array angle_diff in degrees")


@PROPS
@given(angle, angle)
def test_angle_diff_is_the_signed_smallest_difference(a, b):
    d = geo.angle_diff(a, b)
    assert -math.pi <= d < math.pi
    assert abs(geo.wrap_angle(b + d - a)) < 1e-9 or abs(abs(geo.wrap_angle(b + d - a)) - 2 * math.pi) < 1e-9


def test_circular_mean_across_the_cut():
    m = geo.circular_mean(np.radians([179.0, -179.0]))
    assert abs(geo.angle_diff(m, math.pi)) < 1e-12, f"mean of 179 and -179 deg = {math.degrees(m)} deg, expected 180"
    m = geo.circular_mean(np.radians([170.0, -170.0, 180.0]))
    assert abs(geo.angle_diff(m, math.pi)) < 1e-12, f"mean = {math.degrees(m)} deg"
    m = geo.circular_mean(np.radians([10.0, 350.0]))
    assert abs(m) < 1e-12, f"mean of 10 and 350 deg = {math.degrees(m)} deg, expected 0"


def test_circular_mean_weighted_and_cancelling():
    m = geo.circular_mean([0.0, math.pi / 2], weights=[1.0, 1.0])
    assert abs(m - math.pi / 4) < 1e-12
    m = geo.circular_mean([0.0, math.pi / 2], weights=[1.0, 0.0])
    assert abs(m) < 1e-12
    with pytest.raises(GeometryError, match="circular_mean"):
        geo.circular_mean([0.0, math.pi])


# --- averaging -----------------------------------------------------------------------------

def test_average_of_identical_poses_is_exact():
    rng = np.random.default_rng(6)
    for _ in range(20):
        T = random_transform(rng)
        n = int(rng.integers(1, 6))
        avg = geo.average_transforms([T] * n, weights=rng.uniform(0.1, 2.0, size=n))
        assert_close(avg, T, 1e-12, "average of identical poses")


def test_average_of_identical_half_turns_is_exact():
    R = axis_angle_matrix([1, 2, 3], math.pi)
    assert_close(geo.average_rotations([R, R, R]), R, 1e-12, "average of identical 180 deg rotations")


@PROPS
@given(st.floats(-3.0, 3.0), st.floats(-1.5, 1.5), st.floats(0.05, 1.0))
def test_weighted_average_of_two_rotations_about_one_axis(a, delta, w1):
    axis = np.array([0.3, -0.5, 0.8])
    b = a + delta
    w2 = 1.0 - w1
    R = geo.average_rotations([axis_angle_matrix(axis, a), axis_angle_matrix(axis, b)], weights=[w1, w2])
    # The chordal (quaternion) mean of rotations about one axis is that axis, at the weighted
    # circular mean of the angles; for nearby angles that is the weighted angle itself.
    expected = geo.circular_mean([a, b], [w1, w2])
    assert_close(R, axis_angle_matrix(axis, expected), 1e-9, "rotation about the common axis")
    linear = w1 * a + w2 * b
    assert_close(R, axis_angle_matrix(axis, linear), 0.05 * delta ** 2 + 1e-9,
                 f"rotation at the weighted angle {linear} (delta {delta})")


def test_equal_weight_average_of_two_rotations_is_the_midpoint():
    rng = np.random.default_rng(7)
    for _ in range(20):
        axis = rng.normal(size=3)
        a, b = rng.uniform(-math.pi, math.pi, size=2)
        if abs(geo.angle_diff(a, b)) > math.pi - 0.1:
            continue
        R = geo.average_rotations([axis_angle_matrix(axis, a), axis_angle_matrix(axis, b)])
        mid = b + geo.angle_diff(a, b) / 2
        assert_close(R, axis_angle_matrix(axis, mid), 1e-9, f"mean of {a} and {b}")


def test_average_rotations_insensitive_to_quaternion_sign():
    # 179 and -179 deg about z: their canonical (w >= 0) quaternions have opposite z signs;
    # adding quaternions naively would give the identity instead of the half turn.
    R = geo.average_rotations([geo.rot_z(math.radians(179)), geo.rot_z(math.radians(-179))])
    assert_close(R, geo.rot_z(math.pi), 1e-12, "mean of 179 and -179 deg about z (expected the half turn)")
    rng = np.random.default_rng(8)
    axis = rng.normal(size=3)
    # Symmetric offsets around the half turn: the mean is the half turn itself.
    Rs = [axis_angle_matrix(axis, math.pi + d) for d in (-0.05, -0.02, 0.0, 0.02, 0.05)]
    R = geo.average_rotations(Rs)
    assert_close(R, axis_angle_matrix(axis, math.pi), 1e-12, "mean of rotations around a half turn")


def _markley_mean(Rs, weights) -> np.ndarray:
    """The former hand-written average: eigenvector of sum w q q^T, quaternion signs flipped at
    random (the method must not care), independent of the core."""
    rng = np.random.default_rng(0)
    quats = []
    for R in Rs:
        w = math.sqrt(max(1.0 + np.trace(R), 0.0)) / 2.0  # valid away from a half turn (w > 0 here)
        q = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 4.0 * w * w]) / (4.0 * w)
        quats.append(q * rng.choice([-1.0, 1.0]))
    quats = np.array(quats)
    M = (quats * (np.asarray(weights) / np.sum(weights))[:, None]).T @ quats
    x, y, z, w = np.linalg.eigh(M)[1][:, -1]
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def test_average_rotations_equals_the_markley_eigenvector_formula():
    # SciPy's Rotation.mean replaced a hand-written Markley average: same result on seeded draws.
    rng = np.random.default_rng(9)
    for _ in range(50):
        n = int(rng.integers(2, 8))
        base = axis_angle_matrix(rng.normal(size=3), rng.uniform(0.0, 1.2))
        Rs = [base @ axis_angle_matrix(rng.normal(size=3), rng.uniform(0.0, 0.3)) for _ in range(n)]
        weights = rng.uniform(0.1, 2.0, size=n)
        assert_close(geo.average_rotations(Rs, weights), _markley_mean(Rs, weights), 1e-9, "Rotation.mean vs Markley")


def test_average_rotations_is_close_to_the_noisy_truth():
    rng = np.random.default_rng(10)
    truth = random_rotation(rng)
    Rs = [truth @ geo.rotation_from_rvec(rng.normal(scale=0.02, size=3)) for _ in range(400)]
    err = geo.rotation_angle(truth.T @ geo.average_rotations(Rs))
    assert err < 0.005, f"mean of 400 rotations with 0.02 rad noise is {err:.4f} rad from the truth"


def test_average_transforms_translation_is_weighted_mean():
    rng = np.random.default_rng(11)
    Ts = [random_transform(rng) for _ in range(4)]
    w = np.array([1.0, 2.0, 3.0, 4.0])
    avg = geo.average_transforms(Ts, w)
    expected = sum(wi * T[:3, 3] for wi, T in zip(w, Ts)) / w.sum()
    assert_close(avg[:3, 3], expected, 1e-12, "weighted mean translation")
    geo.validate_transform(avg, "average")


def test_average_rejects_bad_weights_and_empty_input():
    T = np.eye(4)
    with pytest.raises(GeometryError, match="empty"):
        geo.average_transforms([])
    with pytest.raises(GeometryError, match="weights"):
        geo.average_transforms([T, T], weights=[1.0])
    with pytest.raises(GeometryError, match="weights"):
        geo.average_transforms([T, T], weights=[1.0, -1.0])
    with pytest.raises(GeometryError, match="weights"):
        geo.average_transforms([T, T], weights=[0.0, 0.0])
    with pytest.raises(GeometryError, match="weights"):
        geo.average_rotations([np.eye(3)], weights=[np.nan])


# --- distances and perturbations ----------------------------------------------------------------

def test_pose_distance_and_rotation_angle():
    T_a = geo.transform_from_se2(1.0, 2.0, 0.3)
    T_b = geo.compose(T_a, geo.transform_from_se2(0.3, -0.4, 0.2))
    d, a = geo.pose_distance(T_a, T_b)
    assert abs(d - 0.5) < 1e-12 and abs(a - 0.2) < 1e-12, f"distance {d}, angle {a}"
    assert geo.rotation_angle(np.eye(3)) == 0.0
    assert abs(geo.rotation_angle(np.diag([1.0, -1.0, -1.0])) - math.pi) < 1e-12


def test_se3_perturb_left_multiplies():
    rng = np.random.default_rng(12)
    T = random_transform(rng)
    delta = np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.3])
    P = geo.se3_perturb(T, delta)
    D = geo.transform_from_rvec_tvec(delta[:3], delta[3:])
    assert_close(P, D @ T, 1e-12, "se3_perturb")
    assert_close(geo.se3_perturb(T, np.zeros(6)), T, 0.0, "zero perturbation")
    assert_close(geo.so3_exp(delta[:3]), D[:3, :3], 0.0, "so3_exp")


# --- validation ---------------------------------------------------------------------------------

def _reflection() -> np.ndarray:
    return np.diag([1.0, 1.0, -1.0])


@pytest.mark.parametrize("value, needle", [
    (np.full((4, 4), np.nan), "NaN"),
    (np.eye(3), "shape"),
    ("not a matrix", "expected"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "orthonormal"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
])
def test_validate_transform_names_the_argument(value, needle):
    with pytest.raises(GeometryError) as info:
        geo.validate_transform(value, "T_map_base")
    msg = str(info.value)
    assert "T_map_base" in msg and needle in msg, msg


def test_geometry_error_is_a_value_error():
    with pytest.raises(ValueError):
        geo.validate_rotation(np.zeros((3, 3)), "R_x")


def test_validation_messages_name_each_argument():
    nan3 = [np.nan, 0.0, 0.0]
    cases = [
        (lambda: geo.make_transform(R=_reflection()), "R"),
        (lambda: geo.make_transform(t=[1.0, 2.0]), "t"),
        (lambda: geo.make_transform(t=nan3), "t"),
        (lambda: geo.transform_from_rvec_tvec(nan3, [0, 0, 0]), "rvec"),
        (lambda: geo.transform_from_rvec_tvec([0, 0, 0], [1, 2]), "tvec"),
        (lambda: geo.transform_from_rvec_tvec([0, 0, 0], nan3), "tvec"),
        (lambda: geo.rvec_tvec_from_transform(np.diag([1.0, 1.0, -1.0, 1.0])), "T"),
        (lambda: geo.matrix_from_quaternion([0, 0, 0, 0]), "quaternion"),
        (lambda: geo.matrix_from_quaternion([0, 0, 0, 2.0], name="marker rotation"), "marker rotation"),
        (lambda: geo.matrix_from_quaternion([0, 0, np.nan, 1.0], name="q_cam"), "q_cam"),
        (lambda: geo.matrix_from_quaternion([0, 0, 1.0]), "quaternion"),
        (lambda: geo.transform_from_translation_quaternion([0, 0, np.nan], [0, 0, 0, 1], name="cam3"),
         "cam3 translation"),
        (lambda: geo.transform_from_translation_quaternion([0, 0, 0], [0, 0, 0, 5], name="cam3"), "cam3 rotation"),
        (lambda: geo.quaternion_from_matrix(np.full((3, 3), np.nan)), "rotation"),
        (lambda: geo.quaternion_from_matrix(np.eye(2)), "rotation"),
        (lambda: geo.average_transforms([np.eye(4), np.full((4, 4), np.nan)]), "transforms[1]"),
        (lambda: geo.inverse(np.eye(3)), "inverse"),
    ]
    for fn, name in cases:
        with pytest.raises(GeometryError) as info:
            fn()
        assert name in str(info.value), f"message {str(info.value)!r} does not name {name!r}"
