"""Corner bias of the package's detector on markers whose white margin saturates the sensor.

A tool beside the benchmarks (not a section of ``bench/run.py``). A bright exposure puts the white
paper around a marker at the sensor's full scale (255); the edge profiles across the black border
are then cut on their light side. An edge locator that takes the centroid of the whole gradient
lobe (``detection.refine_corners_lines``) finds the edge on the dark side: the quad comes out
smaller than the marker, and a marker that looks smaller looks farther away.

The images are synthetic and rendered in the order a camera forms them: the printed marker (black
30, white 230 grey levels, a white margin of 2 modules) warped by a perspective onto a 160 x 160 px
image at 8 x 8 samples per pixel, the lens blur (Gaussian, ``--blur`` px), the pixel's area, the
exposure gain, the sensor noise (``--noise`` grey levels), then the clip to 0..255 and the rounding.
Each draw places the marker at a random rotation (+-0.4 rad), foreshortening (70-100 % of its width)
and position (+-5 px); ``--side`` px across. Seeded.

Printed per gain: the mean outward displacement of the detected corners along the diagonal from
the true centre (px; negative: the quad is smaller), its standard error and the detections. With
the default draws, at gain 0.8 and 1.0 (no saturation) the bias is under 0.01 px; white at 1.15,
1.3 and 1.6 times full scale: see docs/benchmarks.md, Detector.

Run: ``source .ws/env.sh; python bench/saturation_bias.py`` (about 10 s).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Dict, List, Tuple

import cv2
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))

from aruco_ring_localization.detection import Detector  # noqa: E402

#: samples per pixel along each axis while rendering (the pixel's area)
SUPERSAMPLE = 8
#: module size of the generated marker texture, texture px
MODULE_PX = 40
#: the printed sheet's grey levels (black square, white paper)
BLACK, WHITE = 30.0, 230.0
#: image size, px
SIZE = 160


def render(rng: np.random.Generator, gain: float, side: float, blur: float, noise: float
           ) -> Tuple[np.ndarray, np.ndarray]:
    """One synthetic image (mono8) and the true corners (4, 2) of the marker's black square."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_1000)
    marker = cv2.aruco.generateImageMarker(dictionary, 7, 7 * MODULE_PX)   # 5x5 bits + the border
    margin = 2 * MODULE_PX
    sheet = cv2.copyMakeBorder(marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
    sheet = (BLACK + (WHITE - BLACK) * sheet.astype(np.float32) / 255.0).astype(np.float32)
    angle = rng.uniform(-0.4, 0.4)
    centre = SIZE / 2 + rng.uniform(-5.0, 5.0, 2)
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * side / 2
    square[:, 0] *= rng.uniform(0.7, 1.0)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    true = square @ rot.T + centre
    far = margin + 7 * MODULE_PX
    src = np.array([[margin, margin], [far, margin], [far, far], [margin, far]], dtype=np.float32)
    # pixel (i, j) covers [j, j + 1) x [i, i + 1) with its centre at j + 0.5 in the fine grid's units
    dst = ((true + 0.5) * SUPERSAMPLE - 0.5).astype(np.float32)
    fine = cv2.warpPerspective(sheet, cv2.getPerspectiveTransform(src, dst), (SIZE * SUPERSAMPLE,) * 2,
                               flags=cv2.INTER_LINEAR, borderValue=120.0)
    if blur > 0:
        fine = cv2.GaussianBlur(fine, (0, 0), blur * SUPERSAMPLE)
    img = fine.reshape(SIZE, SUPERSAMPLE, SIZE, SUPERSAMPLE).mean(axis=(1, 3))
    img = img * gain + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), true


def outward_bias(gain: float, draws: int, side: float, blur: float, noise: float, seed: int) -> Dict[str, float]:
    """Mean outward displacement of the detected corners (px), its standard error, the detections."""
    rng = np.random.default_rng(seed)
    detector = Detector()
    out: List[float] = []
    saturated = 0
    for _ in range(draws):
        img, true = render(rng, gain, side, blur, noise)
        saturated += int((img == 255).any())
        found = detector.detect(img)
        if not found:
            continue
        corners = np.asarray(found[0].corners, dtype=np.float64).reshape(4, 2)
        radial = true - true.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1)[:, None]
        out.append(float(((corners - true) * radial).sum(axis=1).mean()))
    arr = np.array(out)
    return {"gain": gain, "outward_px": float(arr.mean()) if len(arr) else float("nan"),
            "stderr_px": float(arr.std(ddof=1) / np.sqrt(len(arr))) if len(arr) > 1 else float("nan"),
            "detected": len(arr), "draws": draws, "saturated_images": saturated}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gains", default="0.8,1.0,1.15,1.3,1.6", help="exposure gains (white = 230 x gain)")
    ap.add_argument("--draws", type=int, default=60, help="images per gain")
    ap.add_argument("--side", type=float, default=40.0, help="marker side, px")
    ap.add_argument("--blur", type=float, default=0.8, help="lens blur, Gaussian sigma, px")
    ap.add_argument("--noise", type=float, default=1.0, help="sensor noise, grey levels")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    for g in (float(x) for x in a.gains.split(",")):
        print(json.dumps(outward_bias(g, a.draws, a.side, a.blur, a.noise, a.seed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
