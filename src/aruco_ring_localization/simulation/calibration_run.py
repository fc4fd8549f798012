"""A calibration drive in the simulated lab: turn on the spot, drive, turn again (ring calibration).

:func:`calibration_poses` gives the robot's true poses (x, y, yaw) at a frame rate: at each
station of the scene's ``mapping_stations`` a full turn on the spot, then a straight drive
(heading along the path: a differential-drive motion) to the next station. :func:`odometry_poses`
adds the drift of wheel odometry to them (seeded).
"""
from __future__ import annotations

from typing import List, Sequence, Tuple

import numpy as np

from .. import geometry as geo


def calibration_poses(stations: Sequence[Sequence[float]], turn_step_deg: float = 3.0, drive_step: float = 0.05,
                      turns: float = 1.0) -> List[Tuple[float, float, float]]:
    """(x, y, yaw rad) poses: a turn of ``turns`` x 360 deg at each station, straight drives between."""
    out: List[Tuple[float, float, float]] = []
    yaw = float(np.radians(stations[0][2]))
    for k, st in enumerate(stations):
        x, y = float(st[0]), float(st[1])
        n = max(int(round(360.0 * turns / turn_step_deg)), 1)
        for i in range(n + 1):
            out.append((x, y, yaw + np.radians(turn_step_deg) * i))
        yaw = yaw + np.radians(turn_step_deg) * n
        if k + 1 < len(stations):
            nx, ny = float(stations[k + 1][0]), float(stations[k + 1][1])
            heading = float(np.arctan2(ny - y, nx - x))
            # Turn to the heading of the drive, then drive.
            d = float(geo.wrap_angle(heading - yaw))
            m = max(int(abs(np.degrees(d)) / turn_step_deg), 1)
            for i in range(1, m + 1):
                out.append((x, y, yaw + d * i / m))
            yaw = heading
            dist = float(np.hypot(nx - x, ny - y))
            m = max(int(dist / drive_step), 1)
            for i in range(1, m + 1):
                out.append((x + (nx - x) * i / m, y + (ny - y) * i / m, yaw))
    return out


def odometry_poses(poses: Sequence[Tuple[float, float, float]], seed: int = 0, trans_frac: float = 0.01,
                   rot_frac: float = 0.005, rot_noise_deg: float = 0.01) -> List[np.ndarray]:
    """T_odom_base per pose: the true relative motions with seeded wheel-odometry noise per step (the
    usual proportional model: ``trans_frac`` of the distance along and across the motion,
    ``rot_frac`` of the turn plus ``rot_noise_deg``), integrated: it drifts."""
    rng = np.random.default_rng(seed)
    out = [np.eye(4)]
    for a, b in zip(poses[:-1], poses[1:]):
        D = geo.inverse(geo.transform_from_se2(*a)) @ geo.transform_from_se2(*b)
        dx, dy, dyaw = geo.se2_from_transform(D)
        step = float(np.hypot(dx, dy))
        n = geo.transform_from_se2(dx + rng.normal(0.0, trans_frac * step), dy + rng.normal(0.0, trans_frac * step),
                                   dyaw + rng.normal(0.0, rot_frac * abs(dyaw) + np.radians(rot_noise_deg)))
        out.append(out[-1] @ n)
    return out


def rough_ring(true_ring, seed: int = 0, trans: float = 0.05, rot_deg: float = 10.0):
    """The true ring as a drawing gives it: each camera moved by up to ``trans`` m per axis and turned
    by up to ``rot_deg`` per axis of its optical frame (uniform, seeded)."""
    rng = np.random.default_rng(seed)
    extr = {}
    for cam in true_ring.cameras:
        D = np.eye(4)
        D[:3, :3] = geo.rotation_from_rvec(np.radians(rng.uniform(-rot_deg, rot_deg, 3)))
        D[:3, 3] = rng.uniform(-trans, trans, 3)
        extr[cam.name] = cam.T_base_cam @ D
    return true_ring.with_extrinsics(extr)
