"""Corner refinement on markers whose white margin saturates the sensor (detection._unclipped_lobe).

Synthetic images formed as a camera forms them (bench/saturation_bias.py: lens blur, pixel area,
gain, noise, clip at 255). Measured (60 draws per gain): without the saturation handling the quad
comes out -0.112 px per corner too small at white 1.15 x full scale, -0.368 at 1.3, -0.691 at 1.6;
with it +0.004, -0.179, -0.530. Unsaturated images take the unchanged path (-0.008 px).
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
    assert abs(r["outward_px"]) < 0.03, r


def test_heavier_saturation_is_at_least_halved_and_unsaturated_unchanged():
    heavy = saturation_bias.outward_bias(1.3, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert -0.25 < heavy["outward_px"] < 0.0, heavy
    plain = saturation_bias.outward_bias(1.0, draws=30, side=40.0, blur=0.8, noise=1.0, seed=1)
    assert plain["saturated_images"] == 0 and abs(plain["outward_px"]) < 0.02, plain
