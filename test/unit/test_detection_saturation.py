"""Corner refinement on markers whose white margin saturates the sensor (detection._clipped_edge_shift),
and the renderer that saturates as a camera does.

Synthetic images formed as a camera forms them (bench/saturation_bias.py: lens blur, pixel area,
gain, noise, clip at 255). Measured (60 draws per gain): without the saturation handling the quad
comes out -0.112 px per corner too small at white 1.15 x full scale, -0.368 at 1.3, -0.691 at 1.6;
with it -0.034, -0.183, -0.397. Unsaturated images take the unchanged path (-0.008 px).
"""
from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "bench"))

import saturation_bias  # noqa: E402


def test_mildly_saturated_white_margin_does_not_shrink_the_marker():
    r = saturation_bias.outward_bias(1.15, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert r["saturated_images"] == r["draws"] == r["detected"] == 30
    assert -0.06 < r["outward_px"] < 0.0, r


def test_heavier_saturation_is_halved_and_unsaturated_unchanged():
    heavy = saturation_bias.outward_bias(1.3, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert -0.25 < heavy["outward_px"] < 0.0, heavy
    plain = saturation_bias.outward_bias(1.0, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert plain["saturated_images"] == 0 and abs(plain["outward_px"]) < 0.02, plain


def test_the_renderer_saturates_after_the_blur_and_the_noise():
    """simulation/render.py forms a lit image as a camera does: lens blur, light, noise, then the
    clip at full scale. A white margin lit past 255 reads 255 everywhere; with the noise added after
    the clip (the renderer before) only where the noise was not negative, about half of it."""
    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.simulation.ring_sim import RingSimulator
    from aruco_ring_localization.simulation.scene import Scene

    scene = Scene.default()
    ring = CameraRing.load(os.path.join(os.path.dirname(__file__), "..", "..", "config", "ring.yaml"))
    sim = RingSimulator(scene, ring, pixel_noise=0.0, seed=2)
    T = Scene.T_world_base(scene.test_positions[0])
    cam, quads = next((c, q) for c, q in sim.visible(T).items() if q)
    rng = np.random.default_rng(0)
    dark = sim.renderer.render_views([T], cam, rng, photometry=(0.6, 0.0, 0.0))
    bright = sim.renderer.render_views([T], cam, rng, photometry=(1.6, 0.0, 0.0))
    _, quad = quads[0]
    q = np.asarray(quad, dtype=np.float64).reshape(4, 2)
    centre, side = q.mean(axis=0), float(np.linalg.norm(q[1] - q[0]))
    # the white margin: beyond the black square's corners, inside the printed sheet (1 module out)
    out = centre + (q - centre) * (1.0 + 0.8 / 7.0 * 2.0)
    ring_px = [tuple(np.round(p).astype(int)) for p in out]
    white_bright = np.array([bright[y, x] for x, y in ring_px])
    white_dark = np.array([dark[y, x] for x, y in ring_px])
    assert side > 10 and (white_dark < 200).all(), (side, white_dark)
    assert (white_bright == 255).all(), white_bright
