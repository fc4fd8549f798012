"""Corner refinement on markers whose white margin saturates the sensor (detection._stripe_corners,
and detection._clipped_edge_shift where the marker's bits are not given), and the renderer that
saturates as a camera does.

Synthetic images formed as a camera forms them (bench/saturation_bias.py: lens blur, pixel area,
gain, noise, clip at 255). Measured (60 draws per gain): without any saturation handling the quad
comes out -0.112 px per corner too small at white 1.15 x full scale, -0.368 at 1.3, -0.691 at 1.6;
with the gradient fit -0.034, -0.183, -0.397; from the border's centre lines -0.012, -0.016,
-0.024 (30 draws: -0.013, -0.017, -0.025). Unsaturated images take the unchanged path (-0.008 px).
The bench's marker (id 7) has no white bit along its side 3: that side takes the others' offset.
"""
from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "bench"))

import saturation_bias  # noqa: E402

from aruco_ring_localization.detection import Detector, refine_corners_lines  # noqa: E402


def test_mildly_saturated_white_margin_does_not_shrink_the_marker():
    r = saturation_bias.outward_bias(1.15, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert r["saturated_images"] == r["draws"] == r["detected"] == 30
    assert -0.025 < r["outward_px"] < 0.0, r   # the gradient fit: -0.034


def test_heavy_saturation_does_not_shrink_the_marker_and_unsaturated_unchanged():
    for gain in (1.3, 1.6):
        heavy = saturation_bias.outward_bias(gain, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
        assert heavy["detected"] == 30 and -0.05 < heavy["outward_px"] < 0.0, heavy   # gradient fit: -0.18, -0.40
    plain = saturation_bias.outward_bias(1.0, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert plain["saturated_images"] == 0 and abs(plain["outward_px"]) < 0.02, plain


def _saturated_draws(n: int, gain: float):
    rng = np.random.default_rng(1)
    detector = Detector()
    for _ in range(n):
        img, true = saturation_bias.render(rng, gain, 40.0, 0.8, 1.0)
        corners, _ids, _ = detector._detector.detectMarkers(img)   # OpenCV's (SUBPIX), before the refinement
        yield img, true, np.asarray(corners[0], dtype=np.float64).reshape(4, 2)


def _outward(c: np.ndarray, true: np.ndarray) -> float:
    radial = true - true.mean(axis=0)
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    return float(((c - true) * radial).sum(axis=1).mean())


def test_without_the_bits_or_a_white_bit_the_gradient_fit_places_the_edges():
    """refine_corners_lines without the marker's bits, or with bits that have no white one next to
    the border (no stripe to measure: _stripe_corners declines), falls back to the gradient fit."""
    plain, no_white, stripe = [], [], []
    bits7 = Detector()._marker_bits(7)
    assert bits7 is not None and bits7.shape == (5, 5) and not bits7[:, 0].any() and bits7[0].any()
    for img, true, c0 in _saturated_draws(10, 1.3):
        plain.append(_outward(refine_corners_lines(img, c0), true))
        no_white.append(_outward(refine_corners_lines(img, c0, bits=np.zeros((5, 5), dtype=bool)), true))
        stripe.append(_outward(refine_corners_lines(img, c0, bits=bits7), true))
    assert plain == no_white
    assert -0.3 < np.mean(plain) < -0.1, plain          # the gradient fit's bias at white 1.3
    assert -0.05 < np.mean(stripe) < 0.0, stripe


def test_unknown_marker_id_has_no_bits():
    detector = Detector()
    assert detector._marker_bits(100000) is None and detector._marker_bits(-1) is None


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


def test_the_region_search_places_saturated_corners_as_the_whole_image_search_does():
    """The nodes detect through TrackingDetector (regions around the last markers between
    whole-image searches): a saturated marker found in a region gets the same border-stripe corners
    as in a whole-image search, so the node's path takes the marker's bits too."""
    from aruco_ring_localization.detection import TrackingDetector

    rng = np.random.default_rng(3)
    img, true = saturation_bias.render(rng, 1.3, 40.0, 0.8, 1.0)
    whole = Detector().detect(img)
    tracker = TrackingDetector(Detector(), full_every=5, edge_px=0)
    first = tracker.detect(img)                 # a whole-image search (nothing tracked yet)
    second = tracker.detect(img)                # a region search around the marker
    assert [o.marker_id for o in whole] == [o.marker_id for o in first] == [o.marker_id for o in second] == [7]
    for obs in (first, second):
        assert np.allclose(obs[0].corners, whole[0].corners, rtol=0.0, atol=1e-3)   # (the gradient fit: 0.24 px off)
    assert abs(_outward(np.asarray(whole[0].corners), true)) < 0.05   # (the gradient fit: about -0.18 at 1.3)
