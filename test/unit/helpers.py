"""Shared helpers for the unit tests: seeded random poses, small files, assertion messages.

Everything random here takes a ``numpy.random.Generator`` so that each test owns its seed.
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.bundle_adjustment import BAProblem
from aruco_ring_localization.markers import marker_corners

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config"
RING_YAML = CONFIG / "ring.yaml"
CAM0_YAML = CONFIG / "camera_info" / "cam0.yaml"


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed 3x3 rotation (normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def random_transform(rng: np.random.Generator, scale: float = 5.0) -> np.ndarray:
    """A random 4x4 rigid transform with translation components within +-``scale`` m."""
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = rng.uniform(-scale, scale, size=3)
    return T


def axis_angle_matrix(axis, angle: float) -> np.ndarray:
    """Rotation by ``angle`` rad about ``axis`` (normalised here), written independently of the core."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def se2_error(T_est, T_true) -> np.ndarray:
    """(x, y, yaw) of an estimated pose minus the true one's, the yaw wrapped to (-pi, pi]."""
    from aruco_ring_localization import geometry as geo

    e = geo.se2_from_transform(T_est) - geo.se2_from_transform(T_true)
    e[2] = geo.wrap_angle(e[2])
    return e


def max_abs_diff(a, b) -> float:
    """Largest absolute element difference of two arrays (for assertion messages)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape, f"shapes differ: {a.shape} vs {b.shape}"
    return float(np.max(np.abs(a - b))) if a.size else 0.0


def assert_close(a, b, tol: float, what: str = "value") -> None:
    """Assert two arrays agree to ``tol`` element-wise, showing the measured difference."""
    err = max_abs_diff(a, b)
    assert err <= tol, f"{what}: max abs difference {err:.3e} > tolerance {tol:.1e}\n{np.asarray(a)}\nvs\n{np.asarray(b)}"


def write_text(directory: Path, name: str, text: str) -> Path:
    """Write ``text`` to ``directory / name`` and return the path."""
    path = Path(directory) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def assert_config_error_names(exc_info, path, key: Optional[str]) -> None:
    """Check a ConfigError's message names the file ``path`` and (when given) the ``key``."""
    msg = str(exc_info.value)
    assert str(path) in msg, f"error message does not name the file {path}: {msg!r}"
    if key is not None:
        assert key in msg, f"error message does not name the key {key!r}: {msg!r}"


# --- trajectories for the evaluation tests -------------------------------------------------
def stop_and_go(rng: np.random.Generator, n_stops: int = 5, hold: float = 4.0, move: float = 2.0, rate: float = 20.0):
    """A reference that visits ``n_stops`` random poses, holding each for ``hold`` s (seeded).

    Returns stamps, (N, 3) poses, the targets and the (start, end) time of every hold.
    """
    targets = np.column_stack([rng.uniform(-2, 2, n_stops), rng.uniform(-1.5, 1.5, n_stops),
                               rng.uniform(-np.pi, np.pi, n_stops)])
    stamps, poses, holds = [], [], []
    t, prev = 0.0, targets[0]
    for k, goal in enumerate(targets):
        if k:
            for a in np.arange(0, move, 1 / rate):
                f = a / move
                stamps.append(t)
                poses.append([prev[0] + f * (goal[0] - prev[0]), prev[1] + f * (goal[1] - prev[1]),
                              prev[2] + f * np.angle(np.exp(1j * (goal[2] - prev[2])))])
                t += 1 / rate
        start = t
        for _ in np.arange(0, hold, 1 / rate):
            stamps.append(t)
            poses.append(goal.copy())
            t += 1 / rate
        holds.append((start, t - 1 / rate))
        prev = goal
    poses = np.array(poses)
    poses[:, 2] = np.angle(np.exp(1j * poses[:, 2]))
    return np.array(stamps), poses, targets, holds


def tilted_path(stamps: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses of a handheld rig: a 3D loop (z varies) with roll and pitch that change."""
    poses = []
    for t in stamps:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("ZYX", [0.4 * t, 0.15 * np.cos(0.5 * t), 0.2 * np.sin(0.7 * t)]).as_matrix()
        T[:3, 3] = (2.0 * np.cos(0.3 * t), 1.5 * np.sin(0.3 * t), 0.8 + 0.3 * np.sin(0.9 * t))
        poses.append(T)
    return np.stack(poses)


def moved(traj_poses: np.ndarray, T_ref_est: np.ndarray) -> np.ndarray:
    """The poses expressed in a frame ``est`` with ``T_ref_est`` (what an estimate in another frame holds)."""
    T_est_ref = np.linalg.inv(T_ref_est)
    return np.stack([T_est_ref @ P for P in traj_poses])


def synthetic_ba_problem(seed=0, noise=0.0, M=6, S=4, C=3, per=30, size=0.2, focal=800.0):
    """A bundle-adjustment problem: M markers ~4 m in front of a rig of C cameras, seen from S
    stations (station 0 fixed), ``per`` observations drawn with ``noise`` px; returns the problem and
    its true (markers, stations, cameras)."""
    rng = np.random.default_rng(seed)
    T_cams = np.stack([geo.make_transform(geo.rotation_from_rvec([0, 0.2 * k, 0]), [0.1 * k, 0, 0])
                       for k in range(C)])
    T_st = np.stack([geo.make_transform(geo.rotation_from_rvec([0, 0.05 * s, 0]), [0.3 * s, 0.0, 0.1 * s])
                     for s in range(S)])
    T_mk = np.stack([geo.make_transform(geo.rotation_from_rvec([np.pi + rng.normal(0, 0.2), rng.normal(0, 0.3), 0]),
                                        [rng.uniform(-1.5, 1.5), rng.uniform(-0.5, 0.5), rng.uniform(3, 5)])
                     for _ in range(M)])
    om, os_, oc, xy = [], [], [], []
    for _ in range(per):
        m, s, c = rng.integers(M), rng.integers(S), rng.integers(C)
        p = geo.transform_points(geo.inverse(T_cams[c]) @ geo.inverse(T_st[s]) @ T_mk[m], marker_corners(size))
        if np.any(p[:, 2] <= 0.5):
            continue
        om.append(m), os_.append(s), oc.append(c)
        xy.append(p[:, :2] / p[:, 2:] + rng.normal(0, noise / focal, (4, 2)))
    n = len(om)
    prob = BAProblem(T_mk, np.full(M, size), T_st, T_cams, np.array(om), np.array(os_), np.array(oc),
                     np.array(xy), np.full((n, 2), focal), fixed_marker=None, fixed_station=0)
    return prob, (T_mk, T_st, T_cams)


def ba_jacobian_rows(model, rows: slice, seed: int = 1, spread: float = 0.05, h: float = 1e-6):
    """A bundle-adjustment model's analytic Jacobian and its central differences, ``rows`` of both,
    at a seeded random point ``spread`` (rad and m) from its start: ``(analytic, numeric)``."""
    x = np.random.default_rng(seed).normal(0, spread, model.n_params)
    J = model.jacobian(x).toarray()
    Jn = np.stack([(model.residuals(x + h * e) - model.residuals(x - h * e)) / (2 * h)
                   for e in np.eye(model.n_params)], axis=1)
    return J[rows], Jn[rows]


def ba_dense_reference(model, seed: int = 2) -> SimpleNamespace:
    """A model's normal equations ``H, g`` and damped step ``dx`` (damping ``d``) at a seeded random
    point with random weights, beside the dense ``J^T W J`` reference of each (``H_ref, g_ref,
    dx_ref``): the tests compare them."""
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 0.02, model.n_params)
    r = model.residuals(x)
    w = rng.uniform(0.1, 2.0, model.n_res)
    H, g = model.normal_equations(x, r, w)
    J = model.jacobian(x).toarray()
    H_ref, g_ref = J.T @ (w[:, None] * J), J.T @ (w * r)
    d = 1e-3 * np.maximum(np.diag(H_ref), 1e-12)
    return SimpleNamespace(H=H, g=g, d=d, dx=model.solve_damped(H, -g, d), H_ref=H_ref, g_ref=g_ref,
                           dx_ref=np.linalg.solve(H_ref + np.diag(d), -g_ref))
