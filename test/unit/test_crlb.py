"""The joint estimator against the Cramér-Rao bound on seeded simulated frames (corners mode)."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.localization import LocalizationParams, RingLocalizer, crlb_covariance, se2_covariance
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Scene

from helpers import RING_YAML, se2_error

SIGMA = 0.5


def _blocks(sim, ring, truth, T):
    """(T_cam_base, model, map corners) of what each camera sees at T."""
    out = []
    for cam in ring.cameras:
        ids = [i for i, _ in sim.visible_camera(T, cam.name)]
        if ids:
            out.append((cam.T_cam_base, cam.model, np.concatenate([truth.corners(i) for i in ids])))
    return out


@pytest.mark.parametrize("index", [0, 7, 14])
def test_joint_rms_within_125_percent_of_crlb(index):
    scene = Scene.default()
    # Exact extrinsics, declared exact (extrinsics_std 0): the bound is the one for a known rig.
    ring = CameraRing.load(str(RING_YAML)).with_extrinsics_std(0.0, 0.0)
    truth = scene.truth_map()
    sim = RingSimulator(scene, ring, pixel_noise=SIGMA, seed=100 + index)
    # ... and rigid (no vibration declared: the simulated corners have none).
    loc = RingLocalizer(ring, truth, LocalizationParams(fusion="joint", pixel_noise=SIGMA, extrinsic_jitter_deg=0.0,
                                                        extrinsic_jitter_m=0.0))
    T = scene.T_world_base(scene.test_positions[index])
    bound = se2_covariance(crlb_covariance(T, _blocks(sim, ring, truth, T), SIGMA))
    errs, covs = [], []
    rng = np.random.default_rng(index)
    for _ in range(150):
        start = geo.se3_perturb(T, np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.03, 3)])
        res = loc.process(sim.observe(T), prediction=start)
        errs.append(se2_error(res.T_map_base, T))
        covs.append(res.covariance_se2)
    errs = np.array(errs)
    rms_xy = np.sqrt(np.mean(np.sum(errs[:, :2] ** 2, axis=1)))
    crlb_xy = np.sqrt(np.trace(bound[:2, :2]))
    ratio = rms_xy / crlb_xy
    assert 0.75 < ratio < 1.25, f"position RMS {rms_xy * 1000:.3f} mm vs CRLB {crlb_xy * 1000:.3f} mm: ratio {ratio:.3f}"
    yaw_ratio = np.sqrt(np.mean(errs[:, 2] ** 2)) / np.sqrt(bound[2, 2])
    assert 0.75 < yaw_ratio < 1.25, f"yaw RMS / CRLB = {yaw_ratio:.3f}"
    # The estimator's own covariance is honest: close to the bound (same geometry, same sigma).
    cov_xy = np.sqrt(np.trace(np.mean(covs, axis=0)[:2, :2]))
    assert 0.8 < cov_xy / crlb_xy < 1.25, f"reported std {cov_xy * 1000:.3f} mm vs CRLB {crlb_xy * 1000:.3f} mm"
