"""Shared helpers for the unit tests: seeded random poses, small files, assertion messages.

Everything random here takes a ``numpy.random.Generator`` so that each test owns its seed.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

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
