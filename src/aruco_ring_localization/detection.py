"""ArUco marker detection on one image, compatible with UbiquityRobotics' ``aruco_detect``.

* :class:`DetectorParams` — the detector's settings (dictionary, corner refinement, size limits),
  a frozen dataclass with the defaults that reproduce aruco_detect's published test corners.
* :class:`Detector` — wraps OpenCV's ``cv2.aruco.ArucoDetector``: ``detect(gray)`` returns
  :class:`~aruco_ring_localization.detections.MarkerObservation` with corners in aruco_detect order
  (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left of the printed marker; this is OpenCV's
  order), in raw (distorted) pixels of the image.
* :func:`marker_poses` — per-marker pose ``T_cam_marker`` (single-marker IPPE from
  :mod:`pnp`) with aruco_detect's quality figures ``image_error``, ``object_error`` and
  ``fiducial_area`` (definitions in :class:`MarkerPose` and docs/detector.md).
* :func:`image_to_gray` — a ``sensor_msgs/Image`` payload (encoding, size, step, bytes) to a mono8
  array without cv_bridge, with every malformed field reported as a
  :class:`~aruco_ring_localization.errors.MeasurementError` that names the field.
* :func:`annotate` — a BGR copy of the image with the detections drawn (``fiducial_images``).

No rospy here: the ROS node (``ros/detector.py``) and the CLI (``aruco_ring detect``) call this.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Collection, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from . import geometry as geo
from .camera import CameraModel
from .config import param
from .errors import ArucoRingError, ConfigError, MeasurementError
from .detections import MarkerObservation
from .markers import MarkerSizes
from .pnp import solve_marker_ippe

logger = logging.getLogger(__name__)

#: Corner refinement names accepted by :class:`DetectorParams` -> OpenCV constants (``lines``
#: runs OpenCV's SUBPIX first, then :func:`refine_corners_lines`).
CORNER_REFINEMENT = {
    "lines": cv2.aruco.CORNER_REFINE_SUBPIX,
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}

#: Largest predefined dictionary index OpenCV 4.x knows (DICT_ARUCO_MIP_36h12 = 21).
_MAX_DICTIONARY = 21

#: Supported ``sensor_msgs/Image`` encodings -> (channels, bytes per channel).
ENCODINGS = {
    "mono8": (1, 1),
    "8UC1": (1, 1),
    "mono16": (1, 2),
    "16UC1": (1, 2),
    "bgr8": (3, 1),
    "rgb8": (3, 1),
    "bgra8": (4, 1),
    "rgba8": (4, 1),
}


@dataclass(frozen=True)
class DetectorParams:
    """Settings of the ArUco detector (:class:`Detector`)."""

    dictionary: int = param(7, "OpenCV predefined dictionary index, as aruco_detect's dictionary parameter: 7 = "
                               "DICT_5X5_1000 (aruco_detect's default and the simulated lab's), 0 = DICT_4X4_50, "
                               "16 = DICT_ARUCO_ORIGINAL, 17..20 = AprilTag families")
    corner_refinement: str = param("lines", "lines: OpenCV's subpixel refinement, then each corner is the "
                                            "intersection of the two edge lines fitted next to it (unbiased; "
                                            "0.02-0.15 px on sharp markers, where subpix is 0.2-0.5 px inside the "
                                            "true corners of small markers); subpix: cornerSubPix only, exactly "
                                            "aruco_detect's corners (to 1e-4 px on its test images); contour: "
                                            "OpenCV's contour line fit (robust to blur, less precise); apriltag "
                                            "(slow); none (polygon corners, 0.4-1 px off)")
    corner_refinement_win_size: int = param(5, "half window of the subpixel search", unit="px")
    corner_refinement_max_iterations: int = param(30, "iteration cap of the refinement")
    corner_refinement_min_accuracy: float = param(0.01, "stop when a corner moves less than this (aruco_detect "
                                                        "uses 0.01; OpenCV's 0.1 leaves up to 0.03 px)", unit="px")
    corner_refinement_relative_win_size: float = param(0.3, "OpenCV 4.11 caps the subpixel window at this fraction "
                                                            "of the marker's module size")
    min_marker_perimeter_rate: float = param(0.03, "smallest marker perimeter as a fraction of the image's larger "
                                                   "side (0.03: 38 px, about 10 px per side at 1280 px)")
    max_marker_perimeter_rate: float = param(4.0, "largest perimeter, same unit")
    adaptive_thresh_win_size_min: int = param(3, "smallest adaptive threshold window", unit="px")
    adaptive_thresh_win_size_max: int = param(23, "largest adaptive threshold window", unit="px")
    adaptive_thresh_win_size_step: int = param(10, "threshold window step: windows min, min+step, ... <= max are "
                                                   "tried, each about 6 ms per 1280x960 image", unit="px")
    adaptive_thresh_constant: float = param(7.0, "subtracted from the local mean before thresholding")
    error_correction_rate: float = param(0.6, "fraction of the dictionary's correction capacity used (0..1)")
    min_distance_to_border: int = param(3, "markers closer than this to the image border are rejected", unit="px")
    detect_inverted_marker: bool = param(False, "also accept white-on-black markers")

    def __post_init__(self) -> None:
        if isinstance(self.dictionary, bool) or not isinstance(self.dictionary, (int, np.integer)) \
                or not 0 <= int(self.dictionary) <= _MAX_DICTIONARY:
            raise ConfigError(f"expected an OpenCV predefined dictionary index 0..{_MAX_DICTIONARY}, "
                              f"got {self.dictionary!r}", key="dictionary")
        if self.corner_refinement not in CORNER_REFINEMENT:
            raise ConfigError(f"expected one of {sorted(CORNER_REFINEMENT)}, got {self.corner_refinement!r}",
                              key="corner_refinement")
        positive = {
            "corner_refinement_win_size": self.corner_refinement_win_size,
            "corner_refinement_max_iterations": self.corner_refinement_max_iterations,
            "corner_refinement_min_accuracy": self.corner_refinement_min_accuracy,
            "corner_refinement_relative_win_size": self.corner_refinement_relative_win_size,
            "min_marker_perimeter_rate": self.min_marker_perimeter_rate,
            "max_marker_perimeter_rate": self.max_marker_perimeter_rate,
            "adaptive_thresh_win_size_min": self.adaptive_thresh_win_size_min,
            "adaptive_thresh_win_size_max": self.adaptive_thresh_win_size_max,
            "adaptive_thresh_win_size_step": self.adaptive_thresh_win_size_step,
        }
        for key, value in positive.items():
            if not np.isfinite(value) or value <= 0:
                raise ConfigError(f"must be positive, got {value!r}", key=key)
        if self.adaptive_thresh_win_size_min < 3 or \
                self.adaptive_thresh_win_size_max < self.adaptive_thresh_win_size_min:
            raise ConfigError(f"need 3 <= min <= max, got {self.adaptive_thresh_win_size_min}.."
                              f"{self.adaptive_thresh_win_size_max}", key="adaptive_thresh_win_size_min")
        if self.min_marker_perimeter_rate >= self.max_marker_perimeter_rate:
            raise ConfigError("must be below max_marker_perimeter_rate", key="min_marker_perimeter_rate")
        if not 0.0 <= self.error_correction_rate <= 1.0:
            raise ConfigError(f"must be in [0, 1], got {self.error_correction_rate!r}", key="error_correction_rate")
        if self.min_distance_to_border < 0:
            raise ConfigError(f"must be >= 0, got {self.min_distance_to_border!r}", key="min_distance_to_border")

    def threshold_windows(self) -> List[int]:
        """The adaptive threshold windows OpenCV tries, px: min, min + step, ... <= max."""
        lo, hi, step = (int(self.adaptive_thresh_win_size_min), int(self.adaptive_thresh_win_size_max),
                        int(self.adaptive_thresh_win_size_step))
        return list(range(lo, hi + 1, step))

    def opencv(self) -> "cv2.aruco.DetectorParameters":
        """The equivalent ``cv2.aruco.DetectorParameters``."""
        p = cv2.aruco.DetectorParameters()
        p.cornerRefinementMethod = CORNER_REFINEMENT[self.corner_refinement]
        p.cornerRefinementWinSize = int(self.corner_refinement_win_size)
        p.cornerRefinementMaxIterations = int(self.corner_refinement_max_iterations)
        p.cornerRefinementMinAccuracy = float(self.corner_refinement_min_accuracy)
        p.relativeCornerRefinmentWinSize = float(self.corner_refinement_relative_win_size)
        p.minMarkerPerimeterRate = float(self.min_marker_perimeter_rate)
        p.maxMarkerPerimeterRate = float(self.max_marker_perimeter_rate)
        p.adaptiveThreshWinSizeMin = int(self.adaptive_thresh_win_size_min)
        p.adaptiveThreshWinSizeMax = int(self.adaptive_thresh_win_size_max)
        p.adaptiveThreshWinSizeStep = int(self.adaptive_thresh_win_size_step)
        p.adaptiveThreshConstant = float(self.adaptive_thresh_constant)
        p.errorCorrectionRate = float(self.error_correction_rate)
        p.minDistanceToBorder = int(self.min_distance_to_border)
        p.detectInvertedMarker = bool(self.detect_inverted_marker)
        return p


class Detector:
    """ArUco detection on mono8 images (one instance per camera; not thread-safe)."""

    def __init__(self, params: Optional[DetectorParams] = None):
        self.params = params if params is not None else DetectorParams()
        dictionary = cv2.aruco.getPredefinedDictionary(int(self.params.dictionary))
        self._dictionary = dictionary
        self._bits: Dict[int, np.ndarray] = {}   # id -> its inner bits (:meth:`_marker_bits`), as met
        self._detector = cv2.aruco.ArucoDetector(dictionary, self.params.opencv())
        self._roi_params = self.params.opencv()  # perimeter limits rescaled per region (detect_in)
        self._roi_detector = cv2.aruco.ArucoDetector(dictionary, self._roi_params)

    def detect(self, gray: np.ndarray) -> List[MarkerObservation]:
        """Markers in a grayscale image.

        Args:
            gray: (height, width) uint8 image (a 3-channel BGR image is converted).

        Returns:
            One :class:`MarkerObservation` per detected marker, in OpenCV's output order,
            corners (4, 2) float64 raw pixels in aruco_detect order (pixel centres at integer
            coordinates, as OpenCV and aruco_detect).

        Raises:
            MeasurementError: not a 2-D uint8 (or 3-channel uint8) array, or empty.
        """
        img = np.asarray(gray)
        if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if img.ndim != 2 or img.dtype != np.uint8:
            raise MeasurementError(f"image: expected a 2-D uint8 array, got shape {img.shape} dtype {img.dtype}")
        if img.size == 0:
            raise MeasurementError(f"image: empty ({img.shape})")
        return self._refined(img, self._detect_quads(self._detector, img))

    def detect_in(self, gray: np.ndarray, boxes: Sequence[Tuple[int, int, int, int]],
                  window: Optional[int] = None, exclude: Collection[int] = ()) -> List[MarkerObservation]:
        """Markers inside some regions of an image only (the search of :class:`TrackingDetector`).

        Each region is searched as an image of its own, with the perimeter limits rescaled so
        that they mean the same marker sizes as in the whole image; corners come back in the
        whole image's pixels and are refined there. Regions should not overlap (a marker seen in
        two is kept once).

        Args:
            gray: (H, W) uint8 image.
            boxes: (x0, y0, x1, y1) pixel ranges, x1/y1 exclusive, clipped to the image.
            window: search with this one adaptive threshold window (px) instead of the detector's
                windows (each window is a threshold, contour and candidate pass of its own).
            exclude: ids left out (not refined either): markers already found elsewhere.
        """
        img = np.asarray(gray)
        if img.ndim != 2 or img.dtype != np.uint8 or img.size == 0:
            raise MeasurementError(f"image: expected a 2-D uint8 array, got shape {img.shape} dtype {img.dtype}")
        height, width = img.shape
        full = float(max(height, width))
        quads: List[Tuple[int, np.ndarray]] = []
        seen = set(exclude)
        for x0, y0, x1, y1 in boxes:
            x0, y0 = max(0, int(x0)), max(0, int(y0))
            x1, y1 = min(width, int(x1)), min(height, int(y1))
            if x1 - x0 < 8 or y1 - y0 < 8:
                continue
            scale = full / float(max(x1 - x0, y1 - y0))
            p = self._roi_params
            p.minMarkerPerimeterRate = float(self.params.min_marker_perimeter_rate) * scale
            p.maxMarkerPerimeterRate = float(self.params.max_marker_perimeter_rate) * scale
            p.adaptiveThreshWinSizeMin = int(window if window is not None else self.params.adaptive_thresh_win_size_min)
            p.adaptiveThreshWinSizeMax = int(window if window is not None else self.params.adaptive_thresh_win_size_max)
            self._roi_detector.setDetectorParameters(p)
            for marker_id, pts in self._detect_quads(self._roi_detector, img[y0:y1, x0:x1]):
                if marker_id not in seen:
                    seen.add(marker_id)
                    quads.append((marker_id, pts + np.array([x0, y0], dtype=np.float64)))
        return self._refined(img, quads)

    @staticmethod
    def _detect_quads(detector, img: np.ndarray) -> List[Tuple[int, np.ndarray]]:
        try:
            corners, ids, _rejected = detector.detectMarkers(img)
        except cv2.error as exc:
            raise MeasurementError(f"ArUco detection failed: {exc}") from None
        if ids is None or len(ids) == 0:
            return []
        return [(int(i), np.asarray(c, dtype=np.float64).reshape(4, 2)) for c, i in zip(corners, np.asarray(ids).ravel())]

    def _marker_bits(self, marker_id: int) -> Optional[np.ndarray]:
        """(n, n) bool: the marker's inner bits (True: white), row 0 along its side from corner 0 to
        corner 1; None for an id the dictionary does not have."""
        bits = self._bits.get(marker_id)
        if bits is None:
            d = self._dictionary
            if not 0 <= marker_id < d.bytesList.shape[0]:
                return None
            bits = self._bits[marker_id] = cv2.aruco.Dictionary.getBitsFromByteList(
                d.bytesList[marker_id:marker_id + 1], d.markerSize).astype(bool)
        return bits

    def _refined(self, img: np.ndarray, quads: Sequence[Tuple[int, np.ndarray]]) -> List[MarkerObservation]:
        out = []
        for marker_id, pts in quads:
            if self.params.corner_refinement == "lines":
                pts = refine_corners_lines(img, pts, bits=self._marker_bits(marker_id))
            out.append(MarkerObservation(marker_id, pts))
        return out


class TrackingDetector:
    """Search where the markers were: regions around the previous image's markers, the whole image
    every ``full_every`` images and whenever a marker of the previous image is not found again.

    On a ring camera at 10 Hz a marker moves a few pixels between images, so most images need only
    the regions around the markers already seen (10-20 % of a 1280x960 image on the lab): the
    adaptive thresholds, contours and decoding are paid on that area only. What it costs: a marker
    that comes into view (around a corner, into range) is found at the next whole-image search,
    at most ``full_every - 1`` images late. A marker that is lost (moved out of its region,
    occluded) makes the same image searched whole, so a marker in view is never dropped by the
    tracking. A ring camera on a robot that drives and turns on the floor sees markers come in
    mostly through the left and right borders: strips of ``edge_px`` there are searched in every
    image too, so those are found at once.

    Threshold windows in turn (``windows_in_turn``, the default): the strips and the scheduled
    whole-image searches are there to find markers that come into view, and each of the detector's
    adaptive threshold windows is a threshold, contour and candidate pass of its own (3 windows
    over an area cost 2-5 times the smallest alone); so they get ONE window per image, the next one
    the next time, while the regions around the tracked markers get all windows in every image
    (the scheduled search searches them too, so it never drops a tracked marker) and a search
    after a loss, or with nothing tracked, is whole-image with all windows. What it costs: a new
    marker that only some of the windows find (uneven light, blur) is found up to as many strip
    searches, or scheduled whole-image searches, later as there are windows (3 by default: up to
    2 images late in the strips, ``3 * full_every - 1`` away from them). ``full_every`` <= 1
    searches every image whole (the plain :class:`Detector`).

    Args:
        detector: the detector (its parameters apply in the regions too).
        full_every: whole-image search period, images.
        margin: each marker's region grows by this fraction of its size on each side, plus
            ``min_margin_px``.
        min_margin_px: fixed growth of each region, px.
        edge_px: width of the strips along the left and right borders searched in every image, px
            (0: none).
        windows_in_turn: the border strips and the scheduled whole-image searches with one
            threshold window each, in turn (the tracked markers' regions with all); False: all
            windows everywhere.
    """

    def __init__(self, detector: Detector, full_every: int = 5, margin: float = 0.5, min_margin_px: int = 16,
                 edge_px: int = 128, windows_in_turn: bool = True):
        self.detector = detector
        self.windows_in_turn = bool(windows_in_turn)
        self.full_every = int(full_every)
        self.margin = float(margin)
        self.min_margin_px = int(min_margin_px)
        self.edge_px = int(edge_px)
        self._previous: Dict[int, np.ndarray] = {}
        self._since_full = 0
        self._shape: Tuple[int, ...] = ()
        self._windows = detector.params.threshold_windows()
        self._strip_turn = 0  # which threshold window the strips get next
        self._whole_turn = 0  # which one the next scheduled whole-image search gets
        self.full_searches = 0
        self.region_searches = 0

    @property
    def params(self) -> DetectorParams:
        """The detector's settings."""
        return self.detector.params

    def reset(self) -> None:
        """Forget the previous image (the next one is searched whole)."""
        self._previous = {}
        self._since_full = 0

    def regions(self, shape: Tuple[int, int]) -> List[Tuple[int, int, int, int]]:
        """Non-overlapping boxes (x0, y0, x1, y1) around the previous image's markers (searched with
        all threshold windows; the border strips, :meth:`strips`, may overlap them)."""
        height, width = shape
        boxes = []
        for corners in self._previous.values():
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            grow = self.margin * float(np.max(hi - lo)) + self.min_margin_px
            boxes.append([max(0, int(np.floor(lo[0] - grow))), max(0, int(np.floor(lo[1] - grow))),
                          min(width, int(np.ceil(hi[0] + grow)) + 1), min(height, int(np.ceil(hi[1] + grow)) + 1)])
        merged = True
        while merged:  # merge overlapping boxes until none overlap
            merged = False
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    a, b = boxes[i], boxes[j]
                    if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                        boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                        del boxes[j]
                        merged = True
                        break
                if merged:
                    break
        return [tuple(b) for b in boxes]

    def strips(self, shape: Tuple[int, int]) -> List[Tuple[int, int, int, int]]:
        """The left and right border strips (x0, y0, x1, y1), ``edge_px`` wide (none for 0)."""
        height, width = shape
        if self.edge_px <= 0:
            return []
        edge = min(self.edge_px, width)
        if 2 * edge >= width:
            return [(0, 0, width, height)]
        return [(0, 0, edge, height), (width - edge, 0, width, height)]

    def detect(self, gray: np.ndarray) -> List[MarkerObservation]:
        """Markers in the next image of the camera (same contract as :meth:`Detector.detect`)."""
        img = np.asarray(gray)
        if img.shape != self._shape:
            self.reset()  # another camera size: the previous corners mean nothing
            self._shape = img.shape
        out: Optional[List[MarkerObservation]] = None
        if self.full_every > 1 and self._previous and img.ndim == 2 and img.dtype == np.uint8:
            out = self.detector.detect_in(img, self.regions(img.shape))
            known = {o.marker_id for o in out}
            scheduled = self._since_full >= self.full_every - 1
            if scheduled and self.windows_in_turn:
                # the scheduled whole-image search, with one threshold window (in turn) besides the
                # regions' all: what it is for is finding markers that came into view
                window = self._windows[self._whole_turn % len(self._windows)]
                self._whole_turn += 1
                out += self.detector.detect_in(img, [(0, 0, img.shape[1], img.shape[0])], window=window,
                                               exclude=known)
            elif not scheduled:
                strips = self.strips(img.shape)
                if strips:
                    window = None
                    if self.windows_in_turn:
                        window = self._windows[self._strip_turn % len(self._windows)]
                        self._strip_turn += 1
                    out += self.detector.detect_in(img, strips, window=window, exclude=known)
            else:
                out = None  # scheduled whole-image search with all windows
            if out is not None and set(self._previous) - {o.marker_id for o in out}:
                out = None  # a marker was lost: search the whole image now, all windows
            elif out is not None and scheduled:
                self._since_full = 0
                self.full_searches += 1
            elif out is not None:
                self._since_full += 1
                self.region_searches += 1
        if out is None:
            out = self.detector.detect(img)
            self._since_full = 0
            self.full_searches += 1
        self._previous = {o.marker_id: o.corners for o in out}
        return out


# Edge sampling of refine_corners_lines: fraction of each side used next to each corner (the
# middle of a side is left out so lens distortion bends the fitted half-sides less; the first
# 6 % are left out because the corner itself blurs both edges together).
_EDGE_T0, _EDGE_T1 = 0.06, 0.5
_MODULES = 7.0  # modules across a 5x5 marker with its border; only sets the sampling scale
_MIN_EDGE_CONTRAST = 12.0  # grey levels: median dark -> light step across a usable edge
_NEXT = np.array([1, 2, 3, 0])                # corner i -> i + 1
#: grey level from which a sample counts as clipped by the sensor's full scale (uint8 images; an
#: interpolated profile sample within half a level of 255 has a saturated pixel under it)
_SATURATED = 254.5
_HALF = np.array([0, 1, 2, 3, 0, 1, 2, 3])     # half-side -> its side (the corner it starts at)
_I_PREV = np.array([7, 4, 5, 6])             # half-side (i-1 -> i) near its end
_I_NEXT = np.array([0, 1, 2, 3])             # half-side (i -> i+1) near its start
_ROT = np.array([1.0, -1.0])


def _clipped_edge_shift(g: np.ndarray, cut: np.ndarray, mid: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``shift`` (the gradient centroids, (..., )) with, in every profile that has a sample at
    full scale (``cut`` (..., k)), the peak of a Gaussian fitted to its uncut dark -> light steps
    ``g`` (..., k - 1) at positions ``mid``: ln g is a parabola in the position, fitted by least
    squares weighted by g^2, its vertex the edge. A profile whose fit is not a peak (fewer than 3
    steps, no curvature, vertex outside the profile) keeps its centroid."""
    step_cut = cut[..., 1:]
    gu = np.where(step_cut, 0.0, g)
    top = gu.max(axis=-1, keepdims=True)
    use = (gu > 0.1 * top) & (top > 0.0)
    y = np.log(np.where(use, gu, 1.0))
    wt = np.where(use, gu * gu, 0.0)
    m1, m2 = mid, mid * mid
    S0, S1, S2 = wt.sum(-1), (wt * m1).sum(-1), (wt * m2).sum(-1)
    S3, S4 = (wt * m2 * m1).sum(-1), (wt * m2 * m2).sum(-1)
    T0, T1, T2 = (wt * y).sum(-1), (wt * y * m1).sum(-1), (wt * y * m2).sum(-1)
    A = np.stack([np.stack([S0, S1, S2], -1), np.stack([S1, S2, S3], -1), np.stack([S2, S3, S4], -1)], -2)
    rhs = np.stack([T0, T1, T2], -1)
    n = use.sum(-1)
    ok = (n >= 3) & step_cut.any(-1)
    A = np.where(ok[..., None, None], A, np.eye(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        try:
            coef = np.linalg.solve(A, np.where(ok[..., None], rhs, 0.0)[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return shift
        x0 = -coef[..., 1] / (2.0 * coef[..., 2])
    ok &= (coef[..., 2] < 0.0) & np.isfinite(x0) & (np.abs(x0) <= mid[-1])
    return np.where(ok, x0, shift)


#: The black border's sides in the marker's own frame (u right, v down, in modules; corner 0 at the
#: top left, OpenCV's order): each side's outward normal and the direction along it (corner i -> i + 1).
_SIDE_NORMAL = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
_SIDE_ALONG = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
#: Across the border (modules from its centre line, outward positive): the profile's samples. +-1.1
#: reaches 0.6 module into the white margin and into a white bit, and stays 0.4 module from the
#: next row of bits (a black one there would darken the inner end).
_STRIPE_OFFS = np.linspace(-1.1, 1.1, 23)
#: Along the border (modules from a bit's centre): three profiles per white bit, away from the
#: neighbouring bits (a black neighbour's blur would darken one flank).
_STRIPE_ALONG = np.array([-0.1, 0.0, 0.1])
#: Passes of :func:`_stripe_corners` (each from the last one's corners: the profiles' places in the
#: marker's frame are the previous quad's, off by its error; three leave it below 0.01 px).
_STRIPE_PASSES = 3


def _stripe_corners(roi: np.ndarray, c: np.ndarray, bits: np.ndarray) -> Optional[np.ndarray]:
    """The corners (4, 2) from the centre lines of the marker's black border, or None.

    Where a white bit lies inside the border, a profile across the border runs white (the margin),
    black (the border, 1 module), white (the bit): a dark stripe between two sides of the same
    paper under the same light, blurred and clipped alike, so its darkness-weighted centroid is its
    centre whatever the blur and however far the white is above full scale. Each side's centre
    line is found so, in the marker's frame through the homography of the current corners ``c``:
    its offset from where that quad puts it and, with two or more white bits along the side, its
    turn; a side with no white bit next to it takes the others' mean offset (the same paper and
    blur). The border's outer lines lie half a module outside the centre lines, and the corners
    where they meet. Three passes, each from the last one's corners. None (the caller keeps its
    own) when no side has a white bit, a profile has no dark stripe (12 grey levels), or the result
    moves a corner by more than half a module or is not finite.

    Args:
        roi: float image region; ``c`` in its pixels.
        c: (4, 2) corners, OpenCV's order, within a fraction of a module.
        bits: (n, n) the inner bits, True where white, row 0 along side 0 (corner 0 -> 1).
    """
    n = bits.shape[0]
    half = 0.5 * n + 1.0                     # the black square's half side, modules
    centre_line = half - 0.5
    cells = np.arange(n) - 0.5 * (n - 1)    # the bits' centres along a side, modules
    # per side, its bits next to the border in the side's own direction
    white = (bits[0, :], bits[:, n - 1], bits[n - 1, ::-1], bits[::-1, 0])
    side_of, pos = [], []
    for k in range(4):
        at = cells[white[k]]
        side_of.append(np.full(at.size * _STRIPE_ALONG.size, k))
        pos.append((at[:, None] + _STRIPE_ALONG).ravel())
    side_of = np.concatenate(side_of)
    if not side_of.size:
        return None
    pos = np.concatenate(pos)
    nrm, along = _SIDE_NORMAL[side_of], _SIDE_ALONG[side_of]
    # (profiles, samples, 2): the profiles' points in the marker's frame
    pts = (pos[:, None] * along + centre_line * nrm)[:, None, :] + _STRIPE_OFFS[None, :, None] * nrm[:, None, :]
    counts = np.bincount(side_of, minlength=4)
    measured = counts > 0
    square = np.array([[-half, -half], [half, -half], [half, half], [-half, half]], dtype=np.float32)
    module = float(np.sqrt(((c - c[_NEXT]) ** 2).sum(axis=1)).mean()) / (2.0 * half)   # px
    out = c
    for _ in range(_STRIPE_PASSES):
        Hm = cv2.getPerspectiveTransform(square, out.astype(np.float32)).astype(np.float64)
        q = pts.reshape(-1, 2) @ Hm[:, :2].T + Hm[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = (q[:, :2] / q[:, 2:3]).astype(np.float32)
        if not np.isfinite(xy).all():
            return None
        prof = cv2.remap(roi, xy[None, :, 0], xy[None, :, 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).reshape(pts.shape[:2]).astype(np.float64)
        dark = prof.max(axis=1, keepdims=True) - prof
        depth = dark.max(axis=1)
        if depth.min() < _MIN_EDGE_CONTRAST:
            return None
        dark = np.maximum(dark - 0.1 * depth[:, None], 0.0)   # the plateaus' noise out
        shift = (dark * _STRIPE_OFFS).sum(axis=1) / dark.sum(axis=1)   # the stripe's centre, modules outward
        # Per side, the shift as a + b * (position along it): least squares over its profiles
        # (b = 0 with fewer than two white bits there), the mean of the others' a where it has none.
        sw = np.bincount(side_of, pos, 4)
        s_mean = np.where(measured, sw / np.maximum(counts, 1), 0.0)
        d_pos = pos - s_mean[side_of]
        sxx = np.bincount(side_of, d_pos * d_pos, 4)
        sxy = np.bincount(side_of, d_pos * shift, 4)
        b = np.where(sxx > 0.1 * counts, sxy / np.maximum(sxx, 1e-12), 0.0)   # (one bit: var 0.007; two: >= 0.25)
        a = np.where(measured, np.bincount(side_of, shift, 4) / np.maximum(counts, 1) - b * s_mean, 0.0)
        a[~measured] = a[measured].mean()
        # Side k's outer line in the marker's frame: p . nrm_k = half + a_k + b_k (p . along_k);
        # corner i is where sides i - 1 and i meet.
        k1, k2 = np.array([3, 0, 1, 2]), np.arange(4)
        r1 = _SIDE_NORMAL[k1] - b[k1, None] * _SIDE_ALONG[k1]
        r2 = _SIDE_NORMAL[k2] - b[k2, None] * _SIDE_ALONG[k2]
        e1, e2 = half + a[k1], half + a[k2]
        det = r1[:, 0] * r2[:, 1] - r1[:, 1] * r2[:, 0]
        uv = np.stack([(e1 * r2[:, 1] - e2 * r1[:, 1]) / det, (r1[:, 0] * e2 - r2[:, 0] * e1) / det], axis=1)
        q = uv @ Hm[:, :2].T + Hm[:, 2]
        out = q[:, :2] / q[:, 2:3]
        if not np.isfinite(out).all() or float(np.abs(out - c).max()) > 0.5 * module:
            return None
    return out


def refine_corners_lines(gray: np.ndarray, corners, iterations: int = 2, bits: Optional[np.ndarray] = None
                         ) -> np.ndarray:
    """Re-place each corner at the intersection of its two edge lines.

    For each side, points along the half next to each corner are sampled; at each, the intensity
    profile across the edge (outward normal, +-0.6 module, at least +-1.5 px) gives a sub-pixel
    edge position as the centroid of the positive (dark -> light) gradient, which a symmetric blur
    does not shift. A gradient-weighted line is fitted to each half-side, and corner i becomes the
    intersection of the half-sides that meet there. Two passes re-centre the profiles. A corner
    whose lines are parallel, whose edges have a median step below 12 grey levels (no white
    margin, occluded, very dark) or that would move more than two profile half-widths keeps its
    input.

    Where the white margin saturates (grey level 255: a bright exposure), the profile is cut on its
    light side, and the centroid of what is left lies on the dark side of the edge: the marker comes
    out smaller, and so farther away (0.2-0.8 px per edge on the harsh lab's bright frames). There,
    given the marker's ``bits``, the corners are placed from the centre lines of the black border
    instead (:func:`_stripe_corners`): where a white bit lies inside the border, the border is a
    dark stripe between two equally white, equally clipped sides, whose centre neither the blur nor
    the clip moves. Without ``bits``, or where that fails, each cut edge is the peak of a Gaussian
    fitted to the gradient's unclipped steps (:func:`_clipped_edge_shift`).

    Args:
        gray: (H, W) uint8 image.
        corners: (4, 2) initial corners (raw pixels, aruco_detect order), within about 1 px.
        bits: (n, n) the marker's inner bits, True where white (:meth:`Detector._marker_bits`;
            row 0 runs along the side from corner 0 to corner 1), or None.

    Returns:
        (4, 2) refined corners, raw pixels.
    """
    c = np.array(corners, dtype=np.float64).reshape(4, 2)  # a copy
    # About 60 small numpy calls per pass: written for few calls (index arrays instead of np.roll,
    # 2x2 determinants and solutions in closed form), the per-marker cost is Python's, not the math's.
    dd = c[_NEXT] - c
    side = np.sqrt(dd[:, 0] * dd[:, 0] + dd[:, 1] * dd[:, 1])
    h = min(max(0.6 * float(side.mean()) / _MODULES, 1.5), 4.0)
    offs = np.arange(-h, h + 1e-9, 0.5)
    mid = 0.5 * (offs[1:] + offs[:-1])
    ns = int(min(max(float(side.max()) * (_EDGE_T1 - _EDGE_T0), 4.0), 64.0))
    u = np.linspace(_EDGE_T0, _EDGE_T1, ns)
    lo, hi = c.min(axis=0), c.max(axis=0)
    x0 = int(max(np.floor(lo[0] - h - 3), 0))
    y0 = int(max(np.floor(lo[1] - h - 3), 0))
    x1 = int(min(np.ceil(hi[0] + h + 4), gray.shape[1]))
    y1 = int(min(np.ceil(hi[1] + h + 4), gray.shape[0]))
    if x1 - x0 < 4 or y1 - y0 < 4:
        return c
    roi = gray[y0:y1, x0:x1].astype(np.float32)  # float: remap on uint8 would round the profiles
    # A white margin at the sensor's full scale cuts the light side of its edges' profiles; only
    # then are the corners placed otherwise (one max per marker otherwise).
    saturated = bool(roi.max() >= _SATURATED)
    origin = np.array([x0, y0], dtype=np.float64)
    c -= origin
    k = offs.size
    tu = np.concatenate([u, 1.0 - u])  # 8 half-sides: side i near corner i (0..3), near corner i+1 (4..7)

    def passes(c: np.ndarray, clipped_fit: bool) -> np.ndarray:
        for _ in range(iterations):
            a = c[_HALF]                                          # (8, 2) start of the half-side's side
            b = c[_NEXT][_HALF]                                   # its end
            d = b - a
            length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
            if length.min() < 1.0:
                break
            d /= length[:, None]
            n = d[:, ::-1] * _ROT                                 # (d_y, -d_x)
            centre = c.mean(axis=0)
            n *= np.sign(((0.5 * (a + b) - centre) * n).sum(axis=1))[:, None]  # outward
            t = tu.reshape(2, 1, ns) * length.reshape(2, 4, 1)    # (2, 4, ns) -> (8, ns) below
            base = a[:, None, :] + t.reshape(8, ns, 1) * d[:, None, :]                       # (8, ns, 2)
            mx = (base[:, :, 0, None] + offs * n[:, 0, None, None]).astype(np.float32).reshape(8 * ns, k)
            my = (base[:, :, 1, None] + offs * n[:, 1, None, None]).astype(np.float32).reshape(8 * ns, k)
            prof = cv2.remap(roi, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                             ).astype(np.float64).reshape(8, ns, k)
            g = np.maximum(prof[:, :, 1:] - prof[:, :, :-1], 0.0)                          # dark -> light
            w = g.sum(axis=2)
            shift = (g * mid).sum(axis=2) / np.maximum(w, 1e-9)
            if clipped_fit:
                shift = _clipped_edge_shift(g, prof >= _SATURATED, mid, shift)
            p = base + shift[..., None] * n[:, None, :]
            W = w / np.maximum(w.sum(axis=1), 1e-9)[:, None]
            m = (p * W[..., None]).sum(axis=1)
            q = p - m[:, None, :]
            qx, qy = q[..., 0], q[..., 1]
            wx = W * qx
            sxx = (wx * qx).sum(axis=1)
            syy = (W * qy * qy).sum(axis=1)
            sxy = (wx * qy).sum(axis=1)
            ang = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)        # principal direction of each half-side
            nx, ny = -np.sin(ang), np.cos(ang)                   # n . x + c = 0 for each half-side's line
            cl = -(nx * m[:, 0] + ny * m[:, 1])
            ax, ay, ac = nx[_I_PREV], ny[_I_PREV], cl[_I_PREV]   # the two lines that meet at corner i
            bx, by, bc = nx[_I_NEXT], ny[_I_NEXT], cl[_I_NEXT]
            det = ax * by - ay * bx
            # an edge needs a real dark -> light step along most of it (a marker printed without a
            # white margin, or cut by an occluder, has none): otherwise keep OpenCV's corner
            ws = np.sort(w, axis=1)
            contrast = 0.5 * (ws[:, (ns - 1) // 2] + ws[:, ns // 2])  # the median
            edged = contrast >= _MIN_EDGE_CONTRAST
            good = (np.abs(det) > 1e-3) & edged[_I_PREV] & edged[_I_NEXT]
            if not good.any():
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                sol = np.stack([(ay * bc - by * ac) / det, (bx * ac - ax * bc) / det], axis=1)
            step = sol - c
            ok = good & np.isfinite(sol).all(axis=1) & (np.sqrt((step * step).sum(axis=1)) < 2.0 * h)
            c = np.where(ok[:, None], sol, c)
        return c

    if saturated and bits is not None:
        # The profiles' lines (their centroids: cut, but close) start the border's centre lines.
        placed = _stripe_corners(roi, passes(c, False), bits)
        if placed is not None:
            return placed + origin
    return passes(c, saturated) + origin


@dataclass(frozen=True)
class MarkerPose:
    """Pose of one detected marker, with aruco_detect's quality figures.

    Attributes:
        marker_id: ArUco id.
        corners: (4, 2) detected raw pixels, aruco_detect order.
        size: side of the black square used, m.
        T_cam_marker: (4, 4) marker frame in the camera's optical frame (best IPPE solution).
        image_error: aruco_detect's ``image_error``: the MEAN SQUARED reprojection error over the
            4 corners, pixels^2 (its source calls it RMS but never takes the square root; we
            keep its definition so thresholds carry over).
        object_error: aruco_detect's ``object_error``: ``image_error / |c0 - c2| * |t| / size``,
            where ``|c0 - c2|`` is the image diagonal in pixels and ``|t|`` the marker's distance
            in m (aruco_detect divides by the default ``fiducial_len`` even for overridden
            markers; we use the marker's own size).
        fiducial_area: area of the corner quadrilateral in pixels^2 (aruco_detect: Heron's
            formula on triangles (c0, c1, c3) and (c1, c2, c3)).
        ambiguity: IPPE ambiguity ratio (best / second RMS error; near 1: the pose may be flipped).
        T_cam_marker_alt: (4, 4) the other IPPE solution, or None.
    """

    marker_id: int
    corners: np.ndarray
    size: float
    T_cam_marker: np.ndarray
    image_error: float
    object_error: float
    fiducial_area: float
    ambiguity: float
    T_cam_marker_alt: Optional[np.ndarray] = field(default=None, repr=False)


def fiducial_area(corners) -> float:
    """Area (pixels^2) of the quadrilateral c0 c1 c2 c3 as aruco_detect computes it.

    Sum of the triangles (c0, c1, c3) and (c1, c2, c3) by Heron's formula; equal to the polygon
    area for a convex quad.
    """
    c = np.asarray(corners, dtype=np.float64).reshape(4, 2)

    def heron(a, b, d) -> float:
        la, lb, lc = np.linalg.norm(a - b), np.linalg.norm(a - d), np.linalg.norm(b - d)
        s = 0.5 * (la + lb + lc)
        return float(np.sqrt(max(s * (s - la) * (s - lb) * (s - lc), 0.0)))

    return heron(c[0], c[1], c[3]) + heron(c[1], c[2], c[3])


def marker_pose(obs: MarkerObservation, model: CameraModel, size: float, refine: bool = True) -> MarkerPose:
    """Pose and quality figures of one observation (see :class:`MarkerPose`).

    ``refine`` polishes both IPPE solutions by Levenberg-Marquardt on the reprojection error, as
    aruco_detect's ``solvePnP`` (ITERATIVE) does: without it the 403.jpg conformance pose differs
    from aruco_detect's by 1.5 mrad, with it by 0.2 mrad (IPPE's closed form is not the
    least-squares optimum). :func:`pnp.solve_marker_ippe` keeps the unrefined pair when the
    refinement merges the two solutions, so the ambiguity stays visible.

    Raises:
        MeasurementError: degenerate corners or no IPPE solution in front of the camera.
    """
    cand = solve_marker_ippe(obs.corners, size, model, refine=refine)
    T = cand.T_cam_marker
    image_error = float(cand.error) ** 2  # mean squared pixel error, as aruco_detect
    diag = float(np.linalg.norm(obs.corners[0] - obs.corners[2]))
    object_error = image_error / diag * float(np.linalg.norm(T[:3, 3])) / size if diag > 0 else float("inf")
    return MarkerPose(
        marker_id=int(obs.marker_id), corners=np.asarray(obs.corners, dtype=np.float64), size=float(size),
        T_cam_marker=T, image_error=image_error, object_error=float(object_error),
        fiducial_area=fiducial_area(obs.corners), ambiguity=float(cand.ambiguity),
        T_cam_marker_alt=cand.T_cam_marker_alt)


def marker_poses(observations: Sequence[MarkerObservation], model: CameraModel,
                 sizes: MarkerSizes, refine: bool = True) -> List[MarkerPose]:
    """Poses of every observation whose pose can be solved (others are logged and skipped).

    Args:
        observations: detections in raw pixels of the camera ``model``.
        model: the camera's intrinsics (from camera_info).
        sizes: marker side per id, m (``fiducial_len`` + ``fiducial_len_override``).
        refine: Levenberg-Marquardt polish of the IPPE poses (see :func:`marker_pose`).

    Returns:
        :class:`MarkerPose` list in the order of ``observations`` (minus the unsolvable ones).
    """
    out: List[MarkerPose] = []
    for obs in observations:
        try:
            out.append(marker_pose(obs, model, sizes(obs.marker_id), refine=refine))
        except ArucoRingError as exc:
            logger.debug("no pose for marker %d: %s", obs.marker_id, exc)
    return out


def image_to_gray(encoding: str, width: int, height: int, step: int, data, is_bigendian: bool = False) -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` payload into a mono8 array (height, width).

    Args:
        encoding: ``mono8`` (``8UC1``), ``mono16`` (``16UC1``, scaled by 1/256 as cv_bridge),
            ``bgr8``, ``rgb8``, ``bgra8`` or ``rgba8``.
        width, height: image size, pixels (> 0).
        step: bytes per row, >= width * bytes per pixel (padding at row ends is skipped).
        data: the bytes (``bytes``, ``bytearray``, a list of ints or a uint8 array).
        is_bigendian: byte order of 16-bit encodings.

    Returns:
        (height, width) uint8 array (a view of ``data`` for unpadded mono8, else a new array).

    Raises:
        MeasurementError: naming the field — unsupported ``encoding``, zero ``width``/``height``,
            ``step`` too small, or ``data`` shorter than ``step * height``.
    """
    if encoding not in ENCODINGS:
        raise MeasurementError(f"encoding: unsupported image encoding {encoding!r} "
                               f"(supported: {', '.join(ENCODINGS)})")
    channels, depth = ENCODINGS[encoding]
    width, height, step = int(width), int(height), int(step)
    if width <= 0 or height <= 0:
        raise MeasurementError(f"width/height: zero-size image ({width}x{height})")
    row_bytes = width * channels * depth
    if step < row_bytes:
        raise MeasurementError(f"step: {step} bytes per row is less than width {width} x {channels * depth} "
                               f"bytes per pixel = {row_bytes} for {encoding}")
    if isinstance(data, np.ndarray):
        buf = data.reshape(-1).view(np.uint8) if data.dtype != np.uint8 else data.reshape(-1)
    elif isinstance(data, (bytes, bytearray, memoryview)):
        buf = np.frombuffer(data, dtype=np.uint8)
    else:
        buf = np.asarray(data, dtype=np.uint8).reshape(-1)
    need = step * (height - 1) + row_bytes
    if buf.size < need:
        raise MeasurementError(f"data: {buf.size} bytes, expected step {step} x height {height} = {step * height}")
    if buf.size >= step * height:
        rows = buf[:step * height].reshape(height, step)[:, :row_bytes]
    else:  # last row without its padding: still decodable
        rows = np.lib.stride_tricks.as_strided(buf, shape=(height, row_bytes), strides=(step, 1))
    if depth == 2:
        dt = np.dtype(">u2" if is_bigendian else "<u2")
        img16 = np.ascontiguousarray(rows).view(dt).reshape(height, width)
        return (img16 >> 8).astype(np.uint8)
    if channels == 1:
        return rows if rows.flags.c_contiguous else np.ascontiguousarray(rows)
    pix = np.ascontiguousarray(rows).reshape(height, width, channels)
    code = {
        "bgr8": cv2.COLOR_BGR2GRAY, "rgb8": cv2.COLOR_RGB2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY,
    }[encoding]
    return cv2.cvtColor(pix, code)


def annotate(gray: np.ndarray, observations: Sequence[MarkerObservation],
             poses: Sequence[MarkerPose] = (), model: Optional[CameraModel] = None) -> np.ndarray:
    """BGR (height, width, 3) copy of ``gray`` with the detected outlines/ids and pose axes drawn."""
    img = cv2.cvtColor(np.asarray(gray, dtype=np.uint8), cv2.COLOR_GRAY2BGR)
    if observations:
        corners = [np.asarray(o.corners, dtype=np.float32).reshape(1, 4, 2) for o in observations]
        ids = np.array([[o.marker_id] for o in observations], dtype=np.int32)
        cv2.aruco.drawDetectedMarkers(img, corners, ids)
    if model is not None:
        for p in poses:
            axes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64) * p.size
            px = model.project(geo.transform_points(p.T_cam_marker, axes))
            if not np.all(np.isfinite(px)):
                continue
            o = tuple(int(round(v)) for v in px[0])
            for k, colour in ((1, (0, 0, 255)), (2, (0, 255, 0)), (3, (255, 0, 0))):
                cv2.line(img, o, tuple(int(round(v)) for v in px[k]), colour, 2)
    return img


def dictionary_name(index: int) -> str:
    """OpenCV's name of a predefined dictionary index (``DICT_5X5_1000`` for 7), or ``str(index)``."""
    names: Dict[int, str] = {getattr(cv2.aruco, n): n for n in dir(cv2.aruco)
                             if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int)}
    return names.get(int(index), str(index))


__all__ = ["DetectorParams", "Detector", "MarkerPose", "marker_pose", "marker_poses", "fiducial_area",
           "image_to_gray", "annotate", "dictionary_name", "CORNER_REFINEMENT", "ENCODINGS"]
