"""Robot pose from one ring frame: per-camera PnP, the paper's fusion, and a joint estimator.

Pipeline of :meth:`RingLocalizer.process` (paper §II-E, Algorithm 1, steps 2-3):

1. **Per-camera estimates.** For each camera, the detected corners of the mapped markers are
   matched (by id, a dict look-up: the cost grows with the markers in view, not the map size) to
   the map's 3D corners. With two or more markers one PnP over all their corners gives
   ``T_cam_map``; with a single marker both IPPE solutions are considered and the one consistent
   with the prediction (or with the other cameras) is kept when the image cannot tell them
   apart (then the estimate is *ambiguous*), else the one the image prefers. Then
   ``T_map_base = T_map_cam · T_cam_base`` (paper eq. 3). Each estimate carries its RMS
   reprojection error (px), the mean distance to its markers (m) and the mean relative angle
   between the camera's optical axis and the markers' normals (rad; 0 = seen face-on).
2. **Fusion**, ``fusion: paper`` (exactly the paper): an estimate whose reprojection error exceeds
   ``max_reprojection_error`` is discarded; ``Ac_d = (TH_d - dist)/TH_d`` (0 beyond TH_d),
   ``Ac_or = (TH_or - ang)/TH_or`` (0 beyond TH_or), ``Ac = (Ac_d + Ac_or)/2``; the estimate with
   the best Ac is taken, and when other good estimates lie within ``fusion_gap`` (Euclidean
   distance of the positions) of it, the result is their Ac-weighted average (eq. 5), yaw
   averaged on the circle.
   ``fusion: joint`` (beyond the paper): one robot pose from every corner of every camera at
   once through the extrinsics (a generalised multi-camera PnP), minimising the pixel
   reprojection error with a Huber loss by iteratively reweighted Gauss-Newton on SE(3), from the
   prediction or the best per-camera estimate (whichever reprojects better), each camera's
   residuals whitened by its pixel noise *and* its extrinsics' uncertainty (the ring file's
   ``extrinsics_std``, or the covariance the mapping stored with the refined extrinsics):
   :class:`JointProblem` explains the model. Its covariance is the inverse of that information
   (plus the cameras' correlated errors). With exact extrinsics (declared exact) it is the
   maximum-likelihood estimate under Gaussian pixel noise and reaches the Cramér-Rao bound
   (:func:`crlb_covariance`). ``fusion: joint_exact_extrinsics``: the same, taking the
   extrinsics as exact whatever the ring file says (the estimator before the model).
   When every camera sees a single marker, the joint problem is solved from every IPPE pose and
   the lowest cost wins; a rival within ``ambiguity_chi2`` makes the pose ambiguous (the gate
   keeps ambiguous poses out of the filter).

Why Gauss-Newton and not Levenberg-Marquardt or scipy's least_squares: the problem has 6 unknowns
and 30-100 residuals, starts within centimetres of the optimum (the prediction or a per-camera
PnP) and converges in 2-4 iterations; a hand-written step with the analytic Jacobian runs in
~0.1 ms, where scipy's machinery costs about ten times that. A step that increases the cost is
halved (a simple line search), which covers the rare far start.

Residuals are in pixels: each observed corner is undistorted once (``CameraModel.normalize``) and
the residual in normalised coordinates is mapped to pixels by ``K2`` (the pinhole scale), or for a
fisheye lens by the local 2x2 Jacobian of its distortion + K at that corner, without
re-distorting at each iteration (see :class:`JointProblem`).

Frames: ``T_map_base`` is the robot in the marker map's frame. Covariances are 6x6 over
(x, y, z, rotation about map x, y, z) in the map frame (REP-103 order for PoseWithCovariance),
and 3x3 over (x, y, yaw).
"""
from __future__ import annotations

import collections
import functools
import logging
import math
from collections.abc import MutableMapping
from dataclasses import dataclass, field
from typing import Callable, Deque, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from scipy.linalg import lapack as _lapack

from . import geometry as geo
from .camera import CameraModel
from .config import in_radians, param, require_positive
from .errors import ConfigError, MeasurementError
from .detections import RingFrame
from .marker_map import MarkerMap
from .odometry import body_covariance_to_perturbation, body_factor_to_perturbation, displacement_to_transform
from .pnp import solve_marker_ippe, solve_points
from .ring import CameraRing

logger = logging.getLogger(__name__)

#: ``motion(t_ref, t_c) -> (d (3,), cov_d (3, 3))`` or ``(d, cov_d, shared (3, k))``, or None: the
#: robot's displacement between two stamps. ``shared``: the part ``shared · z`` of the displacement's
#: error that every camera of the ring frame has in common, ``z ~ N(0, I_k)`` one draw for all of them
#: (e.g. ``dt`` times the error of the one velocity they are all moved with); ``cov_d`` is the whole
#: covariance (``shared shared^T`` included). Without it the cameras' errors are independent.
MotionModel = Callable[[float, float], Optional[Tuple[np.ndarray, ...]]]

FUSION_METHODS = ("paper", "joint", "joint_exact_extrinsics")

# Rejection reasons (keys of LocalizationResult.rejected).
REJECT_UNKNOWN_ID = "unknown id"
REJECT_REPROJECTION = "reprojection error"
REJECT_PNP = "pnp failed"
REJECT_OUTLIER = "joint outlier"
REJECT_NO_MODEL = "no camera model"


@dataclass(frozen=True)
class LocalizationParams:
    """Parameters of :class:`RingLocalizer` (the localizer's ``estimator`` section, config/localization.yaml)."""

    fusion: str = param("joint", "paper: per-camera PnP and the accuracy-weighted fusion, exactly the paper; "
                                 "joint: one multi-camera PnP over every corner, each camera weighed by its "
                                 "pixel noise and its extrinsics' uncertainty (the ring file's extrinsics_std, "
                                 "or the map's covariance of the refined extrinsics), with the covariance of "
                                 "both (measured better); joint_exact_extrinsics: the same taking the "
                                 "extrinsics as exact (the joint estimate before the noise model, for the "
                                 "ablation)")
    max_reprojection_error: float = param(3.0, "per-camera RMS reprojection error above which a camera's estimate "
                                               "is discarded (paper; it gives no value)", unit="px")
    th_distance: float = param(5.0, "TH_d: Ac_d = (TH_d - dist)/TH_d, 0 beyond (paper: 5 m)", unit="m")
    th_orientation_deg: float = param(60.0, "TH_or: Ac_or = (TH_or - angle)/TH_or, 0 beyond (paper: 60 deg)",
                                      unit="deg")
    fusion_gap: float = param(0.10, "per-camera estimates within this distance of the best one are Ac-averaged",
                              unit="m")
    pixel_noise: float = param(0.5, "1-sigma corner noise used for covariances (the residuals' own RMS when "
                                    "larger); about 0.3-0.5 px for aruco_detect with subpixel refinement", unit="px")
    robust_scale: float = param(8.0, "Huber threshold of the joint estimator: above the 3-5 px that a 0.2 deg "
                                     "calibration error leaves (a smaller one down-weights most corners and IRLS "
                                     "converges only linearly); gross outliers are still down-weighted", unit="px")
    max_iterations: int = param(8, "Gauss-Newton iterations of the joint estimator")
    ambiguity_gate: float = param(0.3, "a single-marker IPPE pose is trusted without a reference only when its "
                                       "ambiguity ratio (err_best / err_second) is below this (and the chi^2 of its "
                                       "two poses differ by ambiguity_chi2 or more)")
    ambiguity_chi2: float = param(9.0, "two distinct poses whose chi^2 (pixel residuals over pixel_noise, whitened "
                                       "by the calibration model in joint) differ by less than this are ambiguous "
                                       "(a likelihood ratio below e^4.5 ~ 90): a marker's two IPPE poses, and, when "
                                       "every camera sees a single marker, the joint solutions from every IPPE pose; "
                                       "an ambiguous pose never enters the filter")
    min_markers_joint: int = param(2, "with fewer marker views in the whole ring (a marker seen by two cameras "
                                      "counts twice: their two viewpoints resolve its ambiguity) the joint "
                                      "estimator falls back to the per-camera fusion (a single view of a single "
                                      "marker is ambiguous)")
    extrinsic_jitter_deg: float = param(0.05, "joint: each camera's extrinsics also jitter from frame to frame by this "
                                              "much (1 sigma per axis of its optical frame; the ring shakes while the "
                                              "robot drives), independently per camera and frame, on top of the "
                                              "calibration's uncertainty; 0 with extrinsic_jitter_m = 0: a rigid ring; "
                                              "with estimate_vibration an upper bound (the data's estimate when smaller)",
                                        unit="deg")
    extrinsic_jitter_m: float = param(0.0001, "joint: the same jitter's translation, 1 sigma per axis", unit="m")
    map_uncertainty: bool = param(True, "joint: each marker's pose in the map is uncertain by the map's own "
                                        "position_std and rotation_std (the mapping's), marginalised in the noise model "
                                        "like the extrinsics: a poorly mapped marker weighs less and the covariance "
                                        "carries the map's error; false: the map taken as exact (as before)")
    estimate_pixel_noise: bool = param(True, "joint: the pixel noise is measured from each frame's residuals (the "
                                             "whitened chi^2 equal to its degrees of freedom, at least min_pixel_noise); "
                                             "each frame is solved at the last frame's noise (pixel_noise before the "
                                             "first) and again at its own when the two differ by more than 25 %; the "
                                             "covariance uses its own; "
                                             "false: pixel_noise, the covariance scaled up when the residuals are "
                                             "larger (as before)")
    min_pixel_noise: float = param(0.05, "joint, estimate_pixel_noise: the least pixel noise the residuals may say",
                                   unit="px")
    exact_when_consistent: bool = param(True, "joint: when a frame's cameras agree with each other through the "
                                              "extrinsics (an F-test: giving each camera its own pose lowers the "
                                              "exact-extrinsics residuals by no more than the pixel noise within the "
                                              "cameras explains, at level consistency_alpha), the pose is the "
                                              "exact-extrinsics solution (the Cramer-Rao optimum of a ring whose "
                                              "calibration the data do not contradict); otherwise the "
                                              "calibration-aware one; false: always the calibration-aware one")
    consistency_alpha: float = param(0.01, "joint, exact_when_consistent: the test's false-alarm rate (the chance "
                                           "that a consistent frame is taken as inconsistent)")
    persistence_window: int = param(30, "joint, exact_when_consistent: the last multi-camera frames over which the "
                                        "cameras' disagreement through the extrinsics is checked for what a "
                                        "calibration error does and noise does not: follow the camera from one "
                                        "marker to another (CalibrationPersistence); while it does not "
                                        "(persistence_max), the frames are solved without the ring file's "
                                        "extrinsics_std (the vibration's only; the map's covariance of refined "
                                        "extrinsics stays), exact_when_consistent as before, the covariance still "
                                        "carrying it; never with a camera the ring declares non-rigid (wiggle); "
                                        "0: the extrinsics_std always")
    persistence_max: float = param(0.25, "joint, persistence_window: the largest correlation, over the window, of a "
                                         "camera's own pose correction between frames in which it sees no common "
                                         "marker (1: a constant extrinsic error alone, 0: none) at which the "
                                         "extrinsics count as borne out by the data")
    persistence_min_pairs: int = param(100, "joint, persistence_window: the least number of such frame pairs (summed "
                                            "over the cameras) the window's verdict needs; fewer: the "
                                            "extrinsics_std stays (on the harsh lab's ring, 2 mm / 0.2 deg off, the "
                                            "first 20-50 pairs showed no correlation, the next 90 and more 0.36-0.56)")
    estimate_vibration: bool = param(False, "joint, persistence_window: the cameras' per-frame jitter is measured from "
                                           "the data over the window (VibrationEstimate: each camera's gradient at the "
                                           "exact-extrinsics optimum, differenced between consecutive frames on the "
                                           "same markers, less what the pixel noise within the cameras explains); "
                                           "with vibration_min_pairs pairs the vibration term is the declared one "
                                           "(extrinsic_jitter_deg, extrinsic_jitter_m) scaled by the estimate's upper "
                                           "one-sigma bound, never above the declared (an upper bound: 0 stays a "
                                           "rigid ring), unless more than two standard errors below zero; false "
                                           "(default: on TagSLAM's test_9 it made the filtered output worse, 1.76 -> "
                                           "2.11 mm median): the declared term always")
    vibration_min_pairs: int = param(20, "joint, estimate_vibration: the least number of frame pairs (summed over "
                                         "the cameras, within persistence_window) the estimate needs; fewer: the "
                                         "declared vibration")
    joint_outlier_threshold: float = param(10.0, "a marker whose RMS residual in the joint solution exceeds this "
                                                 "is dropped (moved or mis-mapped marker) and the pose re-solved; a "
                                                 "final RMS above it rejects the joint solution. Larger than "
                                                 "max_reprojection_error: the joint residuals also carry the "
                                                 "extrinsic calibration error (0.2 deg ~ 3 px)", unit="px")

    def __post_init__(self) -> None:
        if self.fusion not in FUSION_METHODS:
            raise ConfigError(f"expected one of {FUSION_METHODS}, got {self.fusion!r}", key="fusion")
        require_positive(self, "max_reprojection_error", "th_distance", "th_orientation_deg", "pixel_noise",
                         "robust_scale", "min_pixel_noise")
        if self.fusion_gap < 0:
            raise ConfigError(f"must be >= 0, got {self.fusion_gap!r}", key="fusion_gap")
        if not 0.0 < self.consistency_alpha < 1.0:
            raise ConfigError(f"must be in (0, 1), got {self.consistency_alpha!r}", key="consistency_alpha")
        for key in ("persistence_window", "persistence_min_pairs", "vibration_min_pairs"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"must be >= 0, got {getattr(self, key)!r}", key=key)
        if not -1.0 <= self.persistence_max <= 1.0:
            raise ConfigError(f"must be in [-1, 1], got {self.persistence_max!r}", key="persistence_max")
        for key in ("extrinsic_jitter_deg", "extrinsic_jitter_m"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"must be >= 0, got {getattr(self, key)!r}", key=key)

    th_orientation = in_radians("th_orientation_deg")


@dataclass
class CameraEstimate:
    """One camera's estimate of the robot pose (paper Algorithm 1, step 2).

    Attributes:
        camera: ring camera name.
        marker_ids: the mapped markers it used.
        T_map_cam, T_map_base: (4, 4) poses in the map frame.
        reprojection_error: RMS over its corners, px.
        distance: mean distance camera -> marker centres, m.
        angle: mean angle between the optical axis and the markers' inward normals, rad.
        accuracy: the paper's Ac in [0, 1].
        ambiguity: IPPE ambiguity ratio for a single marker (0 for several markers).
        ambiguous: a single marker whose two IPPE poses the image does not tell apart (ratio
            above ``ambiguity_gate``): the one nearer the reference was taken.
        valid: False when discarded (``reject_reason`` says why).
        covariance: 6x6 covariance of ``T_map_base`` from this camera alone (see module doc).
    """

    camera: str
    marker_ids: List[int]
    T_map_cam: np.ndarray
    T_map_base: np.ndarray
    reprojection_error: float
    distance: float
    angle: float
    accuracy: float = 0.0
    ambiguity: float = 0.0
    ambiguous: bool = False
    valid: bool = True
    reject_reason: str = ""
    covariance: Optional[np.ndarray] = None

    @property
    def se2(self) -> np.ndarray:
        return geo.se2_from_transform(self.T_map_base)


class LazyMapping(MutableMapping):
    """A dict filled by ``fill(d)`` when first read or written (per-camera estimates that most
    frames never read). Copies and pickles are plain dicts."""

    __slots__ = ("_fill", "_data")

    def __init__(self, fill: Callable[[dict], None]):
        self._fill: Optional[Callable[[dict], None]] = fill
        self._data: dict = {}

    def _get(self) -> dict:
        fill = self._fill
        if fill is not None:
            self._fill = None   # first: a fill that reads the mapping sees what it wrote so far
            fill(self._data)
        return self._data

    def __getitem__(self, key):
        return self._get()[key]

    def __setitem__(self, key, value) -> None:
        self._get()[key] = value

    def __delitem__(self, key) -> None:
        del self._get()[key]

    def __iter__(self):
        return iter(self._get())

    def __len__(self) -> int:
        return len(self._get())

    def __contains__(self, key) -> bool:
        return key in self._get()

    def __repr__(self) -> str:
        return repr(self._get())

    def copy(self) -> dict:
        return dict(self._get())

    def __copy__(self) -> dict:
        return dict(self._get())

    def __deepcopy__(self, memo) -> dict:
        import copy
        return copy.deepcopy(self._get(), memo)

    def __reduce__(self):
        return dict, (dict(self._get()),)


@dataclass
class LocalizationResult:
    """What one ring frame says about the robot pose.

    Attributes:
        stamp: ring frame time, s.
        estimates: camera name -> its estimate (valid or not).
        T_map_base: fused (4, 4) pose, or None when no camera gave a usable estimate.
        covariance: 6x6 over (x, y, z, rx, ry, rz) in the map frame, or None.
        method: ``paper``, ``joint`` or ``""`` (no pose).
        used_cameras: cameras whose data made the pose.
        marker_ids: mapped markers in view (all cameras).
        rejected: counts of dropped detections/estimates by reason.
        residual_rms: RMS reprojection error of the final pose over the corners it used, px.
        n_points: corners used by the final pose.
        iterations: Gauss-Newton iterations (joint).
        ambiguous: the data admit another, distinct pose about as well (a single-marker
            ambiguity nothing else resolves); the pose given is the one nearer the prediction.
            It was chosen by the prediction, so it cannot confirm, start or re-start a track:
            the gate keeps it out of the filter.
        alternatives: those other poses, (4, 4) ``T_map_base`` each (empty unless ambiguous).
        extrinsics_consistent: the joint pose took the extrinsics as exact because the cameras
            agreed with each other through them (``exact_when_consistent``).
        calibration_cleared: the frame was solved without the ring's calibration uncertainty (the
            vibration's only): over the last frames the cameras' disagreement did not follow them
            (``persistence_window``).
    """

    stamp: float
    estimates: Dict[str, CameraEstimate] = field(default_factory=dict)
    T_map_base: Optional[np.ndarray] = None
    covariance: Optional[np.ndarray] = None
    method: str = ""
    used_cameras: List[str] = field(default_factory=list)
    marker_ids: List[int] = field(default_factory=list)
    rejected: Dict[str, int] = field(default_factory=dict)
    residual_rms: float = float("nan")
    n_points: int = 0
    iterations: int = 0
    ambiguous: bool = False
    alternatives: List[np.ndarray] = field(default_factory=list)
    extrinsics_consistent: bool = False
    calibration_cleared: bool = False

    @property
    def ok(self) -> bool:
        return self.T_map_base is not None

    @property
    def se2(self) -> Optional[np.ndarray]:
        """(x, y, yaw) of the fused pose, or None."""
        return None if self.T_map_base is None else geo.se2_from_transform(self.T_map_base)

    @property
    def covariance_se2(self) -> Optional[np.ndarray]:
        """3x3 covariance over (x, y, yaw), or None."""
        return None if self.covariance is None else se2_covariance(self.covariance)


def se2_covariance(cov6: np.ndarray) -> np.ndarray:
    """(x, y, yaw) block of a 6x6 (x, y, z, rx, ry, rz) covariance (rz ~ yaw for a level robot)."""
    return np.asarray(cov6)[_SE2_BLOCK]   # (advanced indexing: a copy)


#: the (x, y, yaw) rows and columns of a 6x6 (x, y, z, rx, ry, rz) covariance (np.ix_ once, not per call)
_SE2_BLOCK = np.ix_([0, 1, 5], [0, 1, 5])


# --- the paper's accuracy weights and fusion ------------------------------------------------

def accuracy_weight(distance: float, angle: float, th_distance: float = 5.0,
                    th_orientation: float = float(np.radians(60.0))) -> float:
    """The paper's eq. 4: ``Ac = (Ac_d + Ac_or) / 2``.

    ``Ac_d = (TH_d - dist)/TH_d`` (0 at or beyond TH_d), ``Ac_or = (TH_or - ang)/TH_or`` (0 at or
    beyond TH_or). Distance in m, angle in rad (absolute value is used).
    """
    ac_d = (th_distance - distance) / th_distance if distance < th_distance else 0.0
    ang = abs(angle)
    ac_or = (th_orientation - ang) / th_orientation if ang < th_orientation else 0.0
    return 0.5 * (max(ac_d, 0.0) + max(ac_or, 0.0))


def fuse_paper(estimates: Sequence[CameraEstimate], fusion_gap: float
               ) -> Tuple[Optional[np.ndarray], List[CameraEstimate], np.ndarray]:
    """The paper's fusion over *valid* estimates (their ``accuracy`` already set).

    Takes the estimate with the highest Ac; the valid estimates whose position lies within
    ``fusion_gap`` (m, 3D Euclidean) of it are averaged with weights Ac / sum(Ac) (eq. 5):
    position by the weighted mean, yaw by the weighted circular mean, roll and pitch by the
    weighted mean (they are small). Estimates with Ac = 0 only count when nothing better exists.

    Returns:
        (fused T_map_base or None, the estimates used, their normalised weights).
    """
    good = [e for e in estimates if e.valid]
    if not good:
        return None, [], np.zeros(0)
    best = max(good, key=lambda e: e.accuracy)
    group = [e for e in good if np.linalg.norm(e.T_map_base[:3, 3] - best.T_map_base[:3, 3]) <= fusion_gap]
    w = np.array([e.accuracy for e in group], dtype=np.float64)
    if w.sum() <= 0.0:
        return best.T_map_base.copy(), [best], np.ones(1)
    keep = w > 0.0
    group = [e for e, k in zip(group, keep) if k]
    w = w[keep] / w[keep].sum()
    if len(group) == 1:
        return group[0].T_map_base.copy(), group, w
    pos = np.sum([wi * e.T_map_base[:3, 3] for wi, e in zip(w, group)], axis=0)
    rpys = np.array([geo.rpy_from_matrix(e.T_map_base) for e in group])
    yaw = geo.circular_mean(rpys[:, 2], w)
    roll = float(np.sum(w * rpys[:, 0]))
    pitch = float(np.sum(w * rpys[:, 1]))
    T = np.eye(4)
    T[:3, :3] = geo.matrix_from_rpy(roll, pitch, yaw)
    T[:3, 3] = pos
    return T, group, w


# --- the joint (multi-camera) least-squares problem -----------------------------------------

def _rotation_from_rotvec(w: np.ndarray) -> np.ndarray:
    """(3, 3) ``exp([w]x)`` by Rodrigues' formula on Python floats (the solver's inner loop: scipy's
    Rotation costs ~20 us a call, this ~3); the series to second order below 1e-8 rad (exact there
    to 1e-24)."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    t2 = x * x + y * y + z * z
    if t2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    return np.array([[1.0 - b * (yy + zz), b * xy - a * z, b * xz + a * y],
                     [b * xy + a * z, 1.0 - b * (xx + zz), b * yz - a * x],
                     [b * xz - a * y, b * yz + a * x, 1.0 - b * (xx + yy)]])


def _perturb(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``geometry.se3_perturb`` without input validation (the solver's inner loop): left-multiply
    ``T`` by (exp(w), v) with ``delta = (w, v)``."""
    R = _rotation_from_rotvec(delta)
    out = np.empty((4, 4))
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ T[:3, 3] + delta[3:6]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _rotations_from_rotvecs(W: np.ndarray) -> np.ndarray:
    """(C, 3, 3) ``exp([w]x)`` for (C, 3) rotation vectors: :func:`_rotation_from_rotvec` batched
    (``R = (1 - b t^2) I + a [w]x + b w w^T``; SciPy's Rotation costs ~40 us a call here)."""
    t2 = np.einsum("ci,ci->c", W, W)
    small = t2 < 1e-16
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    a = np.where(small, 1.0, np.sin(t) / t)
    b = np.where(small, 0.5, (1.0 - np.cos(t)) / t2s)
    R = (b[:, None] * W)[:, :, None] * W[:, None, :]
    d = 1.0 - b * t2
    R[:, 0, 0] += d
    R[:, 1, 1] += d
    R[:, 2, 2] += d
    aw = a[:, None] * W
    R[:, 0, 1] -= aw[:, 2]
    R[:, 1, 0] += aw[:, 2]
    R[:, 0, 2] += aw[:, 1]
    R[:, 2, 0] -= aw[:, 1]
    R[:, 1, 2] -= aw[:, 0]
    R[:, 2, 1] += aw[:, 0]
    return R


def _per_camera_poses(T_base_map: np.ndarray, deltas: np.ndarray, T_base_cams: np.ndarray) -> np.ndarray:
    """(C, 4, 4) ``T_map_cam`` for C perturbations ``deltas`` (C, 6) of ``T_base_map`` (batched
    :func:`_perturb`, inverse and extrinsics: one pass of array operations for all cameras)."""
    R = _rotations_from_rotvecs(deltas[:, :3])
    R_bm = R @ T_base_map[:3, :3]                          # rotation of the perturbed T_base_map
    t_bm = R @ T_base_map[:3, 3] + deltas[:, 3:]
    out = np.zeros((len(deltas), 4, 4))
    R_mb = np.transpose(R_bm, (0, 2, 1))
    out[:, :3, :3] = R_mb
    out[:, :3, 3] = -np.matmul(R_mb, t_bm[:, :, None])[:, :, 0]
    out[:, 3, 3] = 1.0
    return out @ T_base_cams


def _inv(T: np.ndarray) -> np.ndarray:
    """Rigid inverse without validation."""
    out = np.empty((4, 4))
    Rt = T[:3, :3].T
    out[:3, :3] = Rt
    out[:3, 3] = -Rt @ T[:3, 3]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


@dataclass
class CameraView:
    """One camera's usable detections of mapped markers, prepared once per ring frame.

    Attributes:
        name: camera name; T_cam_base: (4, 4) extrinsics in force; model: intrinsics.
        ids: marker ids (k); px: (4k, 2) raw pixels; X: (4k, 3) map corners.
        extrinsics_cov: (6, 6) covariance of the extrinsics' error as a left perturbation (w, v)
            of ``T_base_cam`` in the base frame, or None (exact: the estimator as before);
            extrinsics_factor: ``L`` with ``L L^T = extrinsics_cov`` (computed when not given).
        map_factor: (4k, 3, 6) per corner ``F`` with ``F F^T`` the covariance of its map position
            from its marker's pose uncertainty (:func:`marker_map_factor`), or None (exact map).
        shared_factor: (6, k) the part ``shared_factor · z`` of eta (the extrinsics' error, as in
            ``extrinsics_cov``, which includes it) that all views of the frame have in common,
            ``z ~ N(0, I_k)`` one draw for them all (a free-running camera moved with the robot's
            velocity: :meth:`RingLocalizer._moved_extrinsics`), or None (independent of the others).
        xy: (4k, 2) undistorted normalised observations.
        pixel_jacobian: (4k, 2, 2) d pixels / d xy at the observations for a fisheye lens, else None.
    """

    name: str
    T_cam_base: np.ndarray
    model: CameraModel
    ids: List[int]
    px: np.ndarray
    X: np.ndarray
    T_base_cam: Optional[np.ndarray] = None
    extrinsics_cov: Optional[np.ndarray] = None
    extrinsics_factor: Optional[np.ndarray] = None
    map_factor: Optional[np.ndarray] = None
    shared_factor: Optional[np.ndarray] = None
    xy: np.ndarray = field(init=False)
    pixel_jacobian: Optional[np.ndarray] = field(init=False, default=None)

    def __post_init__(self) -> None:
        if self.T_base_cam is None:
            self.T_base_cam = _inv(self.T_cam_base)
        self.xy = self.model.normalize(self.px)
        self.pixel_jacobian = _pixel_jacobian(self.model, self.xy)

    def exact(self) -> "CameraView":
        """The same view with its extrinsics (and the map) taken as exact."""
        v = object.__new__(CameraView)
        v.__dict__.update(self.__dict__)
        v.extrinsics_cov = v.extrinsics_factor = v.map_factor = v.shared_factor = None
        return v

    def subset(self, keep: Sequence[int]) -> "CameraView":
        """The view restricted to markers ``keep`` (indices into ids)."""
        sel = np.concatenate([np.arange(4 * j, 4 * j + 4) for j in keep])
        v = object.__new__(CameraView)
        v.name, v.T_cam_base, v.model, v.T_base_cam = self.name, self.T_cam_base, self.model, self.T_base_cam
        v.extrinsics_cov, v.extrinsics_factor = self.extrinsics_cov, self.extrinsics_factor
        v.shared_factor = self.shared_factor
        v.map_factor = None if self.map_factor is None else self.map_factor[sel]
        v.ids = [self.ids[j] for j in keep]
        v.px, v.X, v.xy = self.px[sel], self.X[sel], self.xy[sel]
        v.pixel_jacobian = None if self.pixel_jacobian is None else self.pixel_jacobian[sel]
        return v


def _pixel_jacobian(model: CameraModel, xy: np.ndarray, h: float = 1e-6) -> Optional[np.ndarray]:
    """(N, 2, 2) derivative of the raw pixels by the undistorted normalised coordinates at ``xy``
    for a fisheye (equidistant) lens, else None (``K2`` is used: see :class:`JointProblem`).

    A fisheye's ideal-pinhole pixels stretch by 1/cos^2 of the angle off the axis (4 at 60 deg):
    there the corners' pixel noise must be carried through the lens' own local scale."""
    if not model.is_fisheye:
        return None
    n = xy.shape[0]
    pts = np.concatenate([xy + (h, 0.0), xy - (h, 0.0), xy + (0.0, h), xy - (0.0, h)])
    px = model.pixels_from_normalized(model.distort_normalized(pts)).reshape(4, n, 2)
    out = np.empty((n, 2, 2))
    out[:, :, 0] = (px[0] - px[1]) / (2.0 * h)
    out[:, :, 1] = (px[2] - px[3]) / (2.0 * h)
    return out


@dataclass
class JointFit:
    """The normal equations of :class:`JointProblem` at one pose.

    Attributes:
        r: (N, 2) pixel residuals; J: (N, 2, 6) their Jacobian; w: (N,) Huber (IRLS) weights.
        H: (6, 6) information of the left perturbation of ``T_base_map`` (whitened: the pixel
            noise and, when modelled, the extrinsics' uncertainty are in it); g: (6,) gradient.
        chi2: the whitened weighted squared residual ``sum_c r_c^T W_c r_c``.
        cost: what the line search compares: ``chi2`` with a calibration model, else the Huber
            cost of the raw residual norms (the estimator as it was before the model).
        H_cam: (C, 6, 6) per-camera information (``H`` is their sum), or None without a model.
        G_cam, b_cam: (C, 6, 6) ``J_c^T D_c J_c`` and (C, 6) ``J_c^T D_c r_c`` per camera (the
            unmarginalised normal equations, for each camera's own step), or None without a model.
    """

    r: np.ndarray
    J: np.ndarray
    w: np.ndarray
    H: np.ndarray
    g: np.ndarray
    chi2: float
    cost: float
    H_cam: Optional[np.ndarray] = None
    G_cam: Optional[np.ndarray] = None
    b_cam: Optional[np.ndarray] = None
    #: With a calibration model: :class:`_Spectrum` of the blocks ``G_cam`` against the problem's
    #: extrinsics factors (what whitening at any pixel noise needs; None: not computed).
    spectrum: Optional["_Spectrum"] = None
    #: :meth:`weighted_squares` once computed (not an init field: a fit made from this one, e.g.
    #: by ``dataclasses.replace`` or :meth:`JointProblem.linear_step`, starts without it).
    _wsq: Optional[np.ndarray] = field(init=False, default=None, repr=False, compare=False)

    def weighted_squares(self) -> np.ndarray:
        """(N,) per corner ``w_i |r_i|^2`` (a non-finite residual counts 0): what the pixel-noise
        search, the refit at the measured noise and the consistency test each summed from ``r``
        (issue 16: the same numbers once per fit). ``r`` and ``w`` are not changed after a fit is
        made (every step makes a new one), so it is computed on first use and kept."""
        if self._wsq is None:
            rr = np.where(np.isfinite(self.r), self.r, 0.0)
            self._wsq = self.w * np.sum(rr * rr, axis=1)
        return self._wsq


@dataclass
class _Spectrum:
    """Per camera, the eigen-decomposition ``L_c^T G_c L_c = U_c diag(lam_c) U_c^T`` of the blocks
    of one fit (``L``: the extrinsics factors it was taken with), as ``LUT = (L U)^T``: with
    ``M_c = sigma^2 I + L_c^T G_c L_c = U (sigma^2 + lam) U^T`` the whitening at any pixel
    noise is diagonal (:meth:`JointProblem._whitened`), so the pixel-noise search and every refit
    at another sigma cost no 6x6 solve. Depends on ``G`` (the pose and Huber weights) and ``L``
    only, not on ``b`` (a linear step keeps it)."""

    L: np.ndarray       # the (C, 6, 6) factors it belongs to (identity-checked before reuse)
    lam: np.ndarray     # (C, 6), clipped at 0
    LUT: np.ndarray     # (C, 6, 6) (L U)^T = U^T L^T

    @staticmethod
    def of(G: np.ndarray, L: np.ndarray, LT: Optional[np.ndarray] = None) -> "_Spectrum":
        """``LT``: ``L`` transposed per camera, when the caller keeps it."""
        if LT is None:
            LT = np.transpose(L, (0, 2, 1))
        lam, U = np.linalg.eigh(LT @ G @ L)
        return _Spectrum(L, np.clip(lam, 0.0, None), np.matmul(U.transpose(0, 2, 1), LT))

    def beta(self, b: np.ndarray) -> np.ndarray:
        """(C, 6) ``U^T L^T b`` per camera."""
        return np.matmul(self.LUT, b[:, :, None])[:, :, 0]


_SKEW_TEMPLATE = np.zeros((0, 3, 7))
_EPS = float(np.finfo(np.float64).eps)
_I6 = np.arange(6)


def _skew_template(n: int) -> np.ndarray:
    """A fresh (n, 3, 7) ``[0 | I | 0]`` (:meth:`JointProblem._rows`' right factor before its skew
    part is written): a copy of a template kept at the largest size asked for."""
    global _SKEW_TEMPLATE
    if _SKEW_TEMPLATE.shape[0] < n:
        t = np.zeros((max(n, 2 * _SKEW_TEMPLATE.shape[0]), 3, 7))
        t[:, [0, 1, 2], [3, 4, 5]] = 1.0
        _SKEW_TEMPLATE = t
    return _SKEW_TEMPLATE[:n].copy()


#: (id of each view's extrinsics covariance and factor, ...) -> (the views' arrays, kept so that
#: the ids stay theirs; stacked covariances, factors, factors transposed): the same cameras'
#: calibration frame after frame is stacked once (:func:`_extrinsics_stacks`).
_EXT_STACKS: Dict[tuple, tuple] = {}


def _extrinsics_stacks(views: Sequence["CameraView"], covs: Sequence[Optional[np.ndarray]]):
    """(C, 6, 6) covariances (zero for an exact view), their factors ``L`` (the view's own, else
    :func:`_psd_factor`) and ``L`` transposed, for ``views``; cached by the arrays' identity (the
    cache holds them, so an id cannot be reused while its entry lives). Read-only."""
    key = tuple((id(c), id(v.extrinsics_factor)) for v, c in zip(views, covs))
    hit = _EXT_STACKS.get(key)
    if hit is not None:
        return hit[1]
    cov = np.stack([np.zeros((6, 6)) if c is None else np.asarray(c) for c in covs])
    factor = np.stack([v.extrinsics_factor if v.extrinsics_factor is not None else _psd_factor(c)
                       for v, c in zip(views, cov)])
    LT = np.ascontiguousarray(np.transpose(factor, (0, 2, 1)))
    for a in (cov, factor, LT):
        a.flags.writeable = False
    if len(_EXT_STACKS) >= 64:
        _EXT_STACKS.clear()
    out = (cov, factor, LT)
    _EXT_STACKS[key] = ([(c, v.extrinsics_factor) for v, c in zip(views, covs)], out)
    return out


class _Layout:
    """What :class:`JointProblem` derives from its views' cameras, extrinsics and corner counts
    alone (not from their pixels): kept across frames for the same cameras seeing as many markers
    (:func:`_layout`). Read-only arrays."""

    def __init__(self, views: Sequence["CameraView"]):
        counts = [v.X.shape[0] for v in views]
        self.cam_index = np.repeat(np.arange(len(views)), counts)
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.counts = np.array(counts)
        self.row_offsets = tuple(2 * int(k) for k in self.offsets)
        A = np.stack([v.model.K for v in views])[:, :2, :2]
        A[:, 1, 0] = 0.0
        self.A = A[self.cam_index]
        #: some view has a fisheye's per-corner lens Jacobian: the problem writes it into a copy of A.
        self.per_frame_A = any(v.pixel_jacobian is not None for v in views)
        self.T_cam_bases = np.stack([v.T_cam_base for v in views])
        self.T_base_cams = np.stack([v.T_base_cam for v in views])
        T_cb = self.T_cam_bases[self.cam_index]
        self.R = T_cb[:, :3, :3]
        self.t = T_cb[:, :3, 3]
        self.AR = np.matmul(self.A, self.R[:, :2, :])
        self.R2 = self.R[:, 2:3, :].copy()
        for a in (self.cam_index, self.offsets, self.counts, self.A, self.T_cam_bases, self.T_base_cams, self.R,
                  self.t, self.AR, self.R2):
            a.flags.writeable = False


#: (per view: id of its model, T_cam_base, T_base_cam, corner count; fisheye or not) -> (the views'
#: objects, kept so that the ids stay theirs; the :class:`_Layout`): a parked or slow robot's frames
#: see the same markers with the same cameras frame after frame (issue 16).
_LAYOUTS: Dict[tuple, tuple] = {}


def _layout(views: Sequence["CameraView"]) -> _Layout:
    """The :class:`_Layout` of ``views``, cached by the identity of their models and extrinsics."""
    key = tuple((id(v.model), id(v.T_cam_base), id(v.T_base_cam), v.X.shape[0], v.pixel_jacobian is None)
                for v in views)
    hit = _LAYOUTS.get(key)
    if hit is not None:
        return hit[1]
    out = _Layout(views)
    if len(_LAYOUTS) >= 64:
        _LAYOUTS.clear()
    _LAYOUTS[key] = ([(v.model, v.T_cam_base, v.T_base_cam) for v in views], out)
    return out


class JointProblem:
    """Corners of several cameras, ready for Gauss-Newton on ``T_base_map``.

    The unknown is ``T_base_map`` (the map in the robot's frame), perturbed on the left:
    ``T_base_map <- exp(delta) · T_base_map`` with ``delta = (w, v)`` (rotation vector, translation).
    A map point X projects in camera c as ``pi(T_cam_base_c · T_base_map · X)``; its residual is
    ``K2 (pi(...) - xy_obs)`` in pixels, with ``K2 = [[fx, s], [0, fy]]`` the camera's intrinsic
    scale: the error of the ideal (undistorted) pinhole camera, as OpenCV's PnP on undistorted
    points. It differs from the raw-pixel error only by the local scale of the lens distortion
    (a few percent at the edge of the lab's lenses), which changes the weighting, not the
    optimum; the Cramér-Rao comparison (with the exact projection) shows the cost of this is
    negligible. A fisheye (equidistant) lens stretches the ideal pinhole image by up to
    1/cos^2 of the angle off the axis, so there ``K2`` is replaced by the lens' local 2x2
    Jacobian at each observed corner (computed once per frame): the residual is then the raw
    pixel error to first order.

    **Calibration-aware noise model.** When the views carry ``extrinsics_cov`` (Sigma_c, the
    error of camera c's extrinsics as a left perturbation eta_c of ``T_base_cam`` in the base
    frame), camera c's residuals are ``r_c = J_c delta + n_c - J_c eta_c``: an extrinsic error
    moves the points in the camera exactly as a robot motion ``-eta_c`` would
    (``T_cam_base_true = T_cam_base · exp(-eta_c)``, to first order), so the same Jacobian
    ``J_c`` carries it. Marginalising eta_c gives camera c the residual covariance
    ``S_c = sigma^2 D_c^-1 + J_c Sigma_c J_c^T`` (D_c: the Huber weights) and the weight
    ``W_c = S_c^-1``, applied by the Woodbury identity on 6x6 blocks only:
    ``J_c^T W_c J_c = (G_c - G_c Sigma_c (sigma^2 I + G_c Sigma_c)^-1 G_c) / sigma^2`` with
    ``G_c = J_c^T D_c J_c`` (and the same for the gradient). This is the maximum-likelihood pose
    under pixel noise *and* extrinsic errors to first order: each camera says where the robot
    is with its own PnP uncertainty plus the extrinsics' uncertainty carried to the robot (the
    lever arm of a camera's rotation error is the whole distance to its markers for the joint
    estimate without the model, and only camera-to-base for this one), and the cameras are
    fused by information. With Sigma_c = 0 it is the joint estimator without the model.

    Args:
        views: the cameras' detections.
        sigma: 1-sigma pixel noise (px) of the whitened information ``H``.
        cross_covariance: optional (6C, 6C) covariance between *different* cameras' eta (the
            diagonal blocks are ignored: they are the views' own ``extrinsics_cov``), e.g. the
            common part a bundle adjustment leaves; it does not change the estimate, only its
            covariance (:meth:`covariance`). The views' ``shared_factor`` (free-running cameras
            moved with one velocity) add their cross terms ``F_c F_d^T`` to it the same way.
    """

    def __init__(self, views: Sequence[CameraView], sigma: float = 1.0,
                 cross_covariance: Optional[np.ndarray] = None):
        self.views = list(views)
        self.sigma = float(sigma)
        self.X = np.concatenate([v.X for v in views])
        self.xy = np.concatenate([v.xy for v in views])
        layout = _layout(self.views)
        #: (N,) camera of each corner; (C + 1,) first corner of each camera; (C,) corners per camera.
        self.cam_index, self.offsets, self.counts = layout.cam_index, layout.offsets, layout.counts
        self._row_offsets = layout.row_offsets   # (C + 1,) first residual row (2 per corner) of each camera
        # Per corner, the 2x2 map from normalised to pixel errors: K2 = [[fx, s], [0, fy]], or a
        # fisheye's local lens Jacobian.
        self.A = layout.A
        if layout.per_frame_A:
            self.A = self.A.copy()
            for k, v in enumerate(views):
                if v.pixel_jacobian is not None:
                    self.A[self.offsets[k]:self.offsets[k + 1]] = v.pixel_jacobian
        #: (C, 4, 4) the views' T_cam_base and T_base_cam.
        self.T_cam_bases, self.T_base_cams = layout.T_cam_bases, layout.T_base_cams
        self.R, self.t = layout.R, layout.t
        self.n = self.X.shape[0]
        covs = [v.extrinsics_cov for v in self.views]
        self.extrinsics_cov: Optional[np.ndarray] = None
        self.extrinsics_factor: Optional[np.ndarray] = None
        self._LT: Optional[np.ndarray] = None   # the extrinsics factors transposed (:meth:`_spectrum`)
        if any(c is not None for c in covs):
            self.extrinsics_cov, self.extrinsics_factor, self._LT = _extrinsics_stacks(self.views, covs)
        self.cross_covariance = cross_covariance
        # The part of the cameras' eta they have in common (free-running cameras moved with one
        # velocity): (C, 6, k) factors, zero for a view without one.
        self.shared_factor: Optional[np.ndarray] = None
        shared = [v.shared_factor for v in self.views]
        if self.extrinsics_cov is not None and any(f is not None for f in shared):
            k = max(np.shape(f)[1] for f in shared if f is not None)
            self.shared_factor = np.zeros((len(self.views), 6, k))
            for c, f in enumerate(shared):
                if f is not None:
                    f = np.asarray(f, dtype=np.float64)
                    self.shared_factor[c, :, :f.shape[1]] = f
        # The map's uncertainty (per corner 3x6 factors), only with a calibration model.
        self.map_factor: Optional[np.ndarray] = None
        if self.extrinsics_cov is not None and any(v.map_factor is not None for v in self.views):
            self.map_factor = np.concatenate([np.zeros((v.X.shape[0], 3, 6)) if v.map_factor is None
                                              else v.map_factor for v in self.views])
        self.marker_ids = np.array([i for v in self.views for i in v.ids], dtype=np.int64)
        self._Axy = np.matmul(self.A, self.xy[:, :, None])[:, :, 0]
        #: (N, 2, 3) ``A R[:2]`` and (N, 1, 3) ``R[2]`` per corner: the Jacobian's constant parts (:meth:`_rows`).
        self._AR = np.matmul(self.A, self.R[:, :2, :]) if layout.per_frame_A else layout.AR
        self._R2 = layout.R2
        # :meth:`_rows`' (N, 3, 7) right factor [-[p_b]x | I | 0]: only the skew part changes per call.
        self._skew = _skew_template(self.n)

    def residuals(self, T_base_map: np.ndarray, jacobian: bool = True):
        """Pixel residuals (N, 2) and, if asked, their Jacobian (N, 2, 6) w.r.t. ``delta``.

        Points at or behind a camera get a zero Jacobian and an infinite residual.
        """
        r, Ja = self._rows(T_base_map, jacobian)
        return r, (None if Ja is None else Ja[:, :, :6])

    def _rows(self, T_base_map: np.ndarray, jacobian: bool = True) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(r (N, 2), ``[J | r]`` (N, 2, 7) or None): :meth:`residuals` with the Jacobian and the
        residual side by side, as the per-camera normal equations read them (one product for
        ``J^T D J``, ``J^T D r`` and ``r^T D r``). Few array operations: at ~80 corners each costs
        about as much as its arithmetic (issue 16)."""
        p_b = self.X @ T_base_map[:3, :3].T + T_base_map[:3, 3]
        p_c = np.matmul(self.R, p_b[:, :, None])[:, :, 0] + self.t
        z = p_c[:, 2]
        bad = z <= 1e-6
        any_bad = bool(bad.any())
        inv_z = 1.0 / (np.where(bad, 1.0, z) if any_bad else z)
        u = p_c[:, :2] * inv_z[:, None]
        A = self.A
        # A (u - xy) = A u - A xy (A xy: once per problem); A u is the Jacobian's third column below.
        Au = np.matmul(A, u[:, :, None])[:, :, 0]
        r = Au - self._Axy
        if any_bad:
            r[bad] = np.inf
        if not jacobian:
            return r, None
        # d u / d p_c = [[1, 0, -u], [0, 1, -v]] / z (u = x/z, v = y/z), so
        # A · du/dp_c = [A[:, 0], A[:, 1], -A u] / z (columns); d p_c / d delta = R [-[p_b]x | I].
        # A · du/dp_c · R = (A R[:2] - (A u) R[2]) / z: A R[:2] is the problem's (:attr:`_AR`).
        AJR = (self._AR - Au[:, :, None] * self._R2) * inv_z[:, None, None]
        B = self._skew   # (N, 3, 7): [-[p_b]x | I | 0], the identity and the zeros kept across calls
        B[:, 0, 1] = p_b[:, 2]
        B[:, 1, 2] = p_b[:, 0]
        B[:, 2, 0] = p_b[:, 1]
        np.negative(p_b[:, 2], out=B[:, 1, 0])   # (written in place: no temporary per entry)
        np.negative(p_b[:, 0], out=B[:, 2, 1])
        np.negative(p_b[:, 1], out=B[:, 0, 2])
        Ja = np.matmul(AJR, B)   # (N, 2, 7), last column zero: the residual's slot
        Ja[:, :, 6] = r
        if any_bad:
            Ja[bad] = 0.0
            Ja[bad, :, 6] = np.inf
        return r, Ja

    @staticmethod
    def _huber(r: np.ndarray, scale: float, e2: Optional[np.ndarray] = None) -> Tuple[float, np.ndarray]:
        """(Huber cost of the per-corner residual norms, IRLS weights); ``e2``: the squared norms
        ``r[:, 0]^2 + r[:, 1]^2`` when the caller has them."""
        if e2 is None:
            e2 = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
        if not e2.size:
            return 0.0, np.ones(0)
        top = float(e2.max())   # NaN or inf when any corner is not finite
        if top <= scale * scale:   # every corner within the scale (usual)
            return 0.5 * float(e2.sum()), np.ones(len(e2))
        e = np.sqrt(e2)
        if not math.isfinite(top):
            w = np.where(np.isfinite(e), np.where(e <= scale, 1.0, scale / np.maximum(e, 1e-12)), 0.0)
            return np.inf, w
        inside = e <= scale
        cost = float(np.where(inside, 0.5 * e * e, scale * (e - 0.5 * scale)).sum())
        return cost, JointProblem._huber_weights(e, scale)

    @staticmethod
    def _huber_weights(e: np.ndarray, scale: float) -> np.ndarray:
        """IRLS weights of finite per-corner residual norms ``e``: scale / e >= 1 exactly where
        e <= scale, so the same weights as where(e <= scale, 1, scale / e)."""
        return np.minimum(scale / np.maximum(e, 1e-12), 1.0)

    def fit(self, T_base_map: np.ndarray, scale: float) -> JointFit:
        """Residuals, Jacobian, weights and the (whitened) normal equations at ``T_base_map``."""
        r, Ja = self._rows(T_base_map)
        J = Ja[:, :, :6]
        e2 = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
        top = float(e2.max()) if e2.size else 0.0   # NaN or inf when any corner is not finite
        if top <= scale * scale:
            # Every corner within the Huber scale (NaN-safe): unit weights, no weighting pass
            # ([J r]^T [J r] directly).
            huber, w, Jw = 0.5 * float(e2.sum()), np.ones(self.n), Ja
        else:
            if self.extrinsics_cov is not None and math.isfinite(top):
                # With a calibration model the cost is the whitened chi2 (_whitened): of the Huber
                # loss only the weights are needed, and that it is finite (here: every r is). The
                # usual frame of the lab has a corner beyond the scale (issue 16: _huber's cost
                # pass was a tenth of a fit).
                huber, w = 0.0, self._huber_weights(np.sqrt(e2), scale)
            else:
                huber, w = self._huber(r, scale, e2)
                if not math.isfinite(huber):   # finite cost: every r finite; else the non-finite rows out
                    Ja[:, :, 6] = np.where(np.isfinite(r), r, 0.0)
            Jw = Ja * w[:, None, None]
        s2 = self.sigma ** 2
        if self.extrinsics_cov is None:
            A7 = np.matmul(Jw.reshape(-1, 7).T, Ja.reshape(-1, 7)) / s2
            return JointFit(r, J, w, A7[:6, :6], A7[:6, 6], float(A7[6, 6]), huber)
        # Per camera, [J_c r_c]^T D_c [J_c r_c] in one product: J_c^T D_c J_c, J_c^T D_c r_c, r_c^T D_c r_c
        # (one BLAS product per camera on its rows: half the cost of the per-corner outer products
        # summed by reduceat at the lab's 8 cameras).
        A7 = np.empty((len(self.counts), 7, 7))
        Ja2, Jw2 = Ja.reshape(-1, 7), Jw.reshape(-1, 7)
        rows = self._row_offsets
        for c in range(len(rows) - 1):
            a, b = rows[c], rows[c + 1]
            np.dot(Jw2[a:b].T, Ja2[a:b], out=A7[c])
        return self._whitened(r, J, w, A7[:, :6, :6], A7[:, :6, 6], A7[:, 6, 6], huber, Gb=A7[:, :6, :])

    def refit(self, fit: JointFit) -> JointFit:
        """``fit`` (of these cameras' rows, at any pixel noise, with a calibration model) at this
        problem's ``sigma``: the residuals, Jacobian and Huber weights do not depend on the pixel
        noise (the Huber scale is in pixels), only the marginalisation of the extrinsics does, so
        this is the 6x6 blocks' part of :meth:`fit` without evaluating the residuals again (and,
        with the fit's :class:`_Spectrum`, without a decomposition)."""
        if fit.G_cam is None or self.extrinsics_factor is None:
            raise ValueError("refit needs a calibration model")
        q = np.add.reduceat(fit.weighted_squares(), self.offsets[:-1])
        huber = 0.0 if np.isfinite(fit.r).all() else np.inf
        return self._whitened(fit.r, fit.J, fit.w, fit.G_cam, fit.b_cam, q, huber, fit.spectrum)

    def _spectrum(self, G: np.ndarray, spectrum: Optional[_Spectrum] = None) -> _Spectrum:
        """``spectrum`` when it belongs to these blocks' extrinsics factors, else computed."""
        if spectrum is not None and spectrum.L is self.extrinsics_factor:
            return spectrum
        if self._LT is None:
            self._LT = np.ascontiguousarray(np.transpose(self.extrinsics_factor, (0, 2, 1)))
        return _Spectrum.of(G, self.extrinsics_factor, self._LT)

    def _whitened(self, r: np.ndarray, J: np.ndarray, w: np.ndarray, G: np.ndarray, b: np.ndarray, q: np.ndarray,
                  huber: float, spectrum: Optional[_Spectrum] = None, Gb: Optional[np.ndarray] = None) -> JointFit:
        """The fit from the per-camera blocks ``G_c = J_c^T D_c J_c``, ``b_c = J_c^T D_c r_c``,
        ``q_c = r_c^T D_c r_c``, the extrinsics marginalised at this problem's ``sigma``.

        With Sigma_c = L_c L_c^T: ``G Sigma (s2 I + G Sigma)^-1 = G L M^-1 L^T`` with
        ``M = s2 I + L^T G L = U (s2 + lam) U^T`` (:class:`_Spectrum`), so with ``P = G L U``,
        ``beta = U^T L^T b`` and ``d = 1 / (s2 + lam)``: ``H_c = (G - P d P^T) / s2``,
        ``g_c = (b - P d beta) / s2``, ``chi2 = sum_c (q_c - beta^T d beta) / s2``. Raises
        LinAlgError when ``M`` is not numerically positive definite (its condition beyond
        1 / machine epsilon: what the Cholesky solves this replaced refused, e.g. a trial pose far
        off, seen on a real recording with eigenvalues 0.04 .. 2e15). ``Gb``: ``[G | b]`` (C, 6, 7)
        when the caller has it side by side already."""
        s2 = self.sigma ** 2
        Gb = np.concatenate([G, b[:, :, None]], axis=2) if Gb is None else Gb
        if spectrum is None or spectrum.L is not self.extrinsics_factor:
            # No decomposition at hand (a fit at a new pose): with the Cholesky factor M = K K^T,
            # G L M^-1 L^T G = Z^T Z for Z = K^-1 L^T G, and the same for b: one batched 6x6
            # factorisation and triangular solve (~25 us for 8 cameras) where an eigen-decomposition
            # costs twice that, needed only by the pixel-noise search (:meth:`_spectrum`, once per
            # frame on the final fit). Refused as the spectrum's test below refuses: M not
            # positive definite, or its pivots spanning more than 1 / machine epsilon.
            if self._LT is None:
                self._LT = np.ascontiguousarray(np.transpose(self.extrinsics_factor, (0, 2, 1)))
            Q = np.matmul(self._LT, Gb)                      # L^T [G | b]
            M = np.matmul(Q[:, :, :6], self.extrinsics_factor)
            C = M.shape[0]
            diag = M.reshape(C, 36)[:, ::7]                  # M's diagonals (a view: M is fresh)
            diag += s2
            K = np.linalg.cholesky(M)                        # raises LinAlgError: not positive definite
            piv = K.reshape(C, 36)[:, ::7]
            piv = piv * piv
            if not piv.min() > _EPS * diag.max():
                raise np.linalg.LinAlgError("whitening: the 6x6 normal matrix is not positive definite")
            Z = np.linalg.solve(K, Q)
            Y = (Gb - np.matmul(Z[:, :, :6].transpose(0, 2, 1), Z)) / s2
            z = Z[:, :, 6]
            chi2 = float(np.asarray(q).sum() - (z * z).sum()) / s2
            if not math.isfinite(huber):
                chi2 = np.inf
            Hg = Y.sum(axis=0)   # [H | g]: the cameras' sums in one reduction (the same numbers)
            return JointFit(r, J, w, Hg[:, :6], Hg[:, 6], chi2, chi2, Y[:, :, :6], G, b, None)
        sp = spectrum
        m = s2 + sp.lam
        if not m.min() > _EPS * m.max():
            raise np.linalg.LinAlgError("whitening: the 6x6 normal matrix is not positive definite")
        d = 1.0 / m
        # [G | b] and Q = U^T L^T [G | b] = [P^T | beta] (P = G L U: G is symmetric): then
        # [H_c | g_c] s2 = [G | b] - P d [P^T | beta] in one product.
        Q = np.matmul(sp.LUT, Gb)
        Qd = Q * d[:, :, None]
        Y = (Gb - np.matmul(Q[:, :, :6].transpose(0, 2, 1), Qd)) / s2
        chi2 = float(np.asarray(q).sum() - (Qd[:, :, 6] * Q[:, :, 6]).sum()) / s2
        if not math.isfinite(huber):
            chi2 = np.inf
        Hg = Y.sum(axis=0)
        return JointFit(r, J, w, Hg[:, :6], Hg[:, 6], chi2, chi2, Y[:, :, :6], G, b, sp)

    def pixel_noise_estimate(self, fit: JointFit, lo: float, hi: float, start: Optional[float] = None) -> float:
        """The pixel noise (px) that makes the whitened residuals of ``fit`` (a fit of this problem,
        with a calibration model) as large as they should be: ``chi2(sigma) = 2N - 6``, within
        ``[lo, hi]`` (``lo`` when they are smaller even there).

        ``chi2(sigma) = sum_c (q_c - b_c^T L_c (sigma^2 I + L_c^T G_c L_c)^-1 L_c^T b_c) / sigma^2``
        falls monotonically with sigma; with the eigen-decomposition ``L_c^T G_c L_c = U Λ U^T`` (the
        fit's :class:`_Spectrum`) it is a scalar function of sigma^2 (no solve per trial), whose
        crossing is found on log sigma by a bracketed Newton iteration, from ``start`` when given
        (the last frame's noise: a parked or slow robot's frames measure nearly the same, so a few
        evaluations fewer; the root is the same to the iteration's 1e-10)."""
        if fit.G_cam is None or self.extrinsics_factor is None:
            raise ValueError("pixel_noise_estimate needs a calibration model")
        q = float(np.sum(fit.weighted_squares()))
        sp = fit.spectrum = self._spectrum(fit.G_cam, fit.spectrum)   # kept: the refit at sigma reuses it
        b2 = (sp.beta(fit.b_cam) ** 2).ravel()   # (U^T L^T b)^2 per camera
        lam = sp.lam.ravel()
        dof = max(2 * self.n - 6, 1)

        def chi2(log_sig: float) -> Tuple[float, float]:   # chi2 and its derivative in log sigma
            s2 = math.exp(2.0 * log_sig)
            den = lam + s2
            t = b2 / den
            c = (q - float(t.sum())) / s2
            return c, 2.0 * float((t / den).sum()) - 2.0 * c

        a0, b0 = float(np.log(lo)), float(np.log(hi))
        a, b = a0, b0
        # Newton on log sigma, kept inside the bracket [a, b] (chi2(a) > dof > chi2(b), monotone):
        # a step that would leave it bisects instead. Converges to 1e-10 in log sigma in a handful
        # of scalar evaluations (the grids this replaced took 5 rounds of 33 for 2e-7).
        # Start at sqrt(q / dof), where the unmarginalised chi2 crosses: an upper bound of the root
        # (the marginalisation only lowers chi2), near it when the extrinsics' part is small.
        # The ends of the bracket are tested after the iteration, and only an end it never moved:
        # with the root below lo (chi2(a0) <= dof) every trial has chi2 <= dof (chi2 falls with
        # sigma), so a stays a0, and with it above hi b stays b0; the iteration itself is the same
        # either way (it starts from the same bracket). Two evaluations of the usual five to eight
        # fewer (issue 16).
        x = min(max(0.5 * math.log(max(q / dof, 1e-300)) if start is None or not start > 0.0 else math.log(start),
                    a), b)
        if not a < x < b:
            x = 0.5 * (a + b)
        for _ in range(60):
            c, dc = chi2(x)
            if c > dof:
                a = x
            else:
                b = x
            x_new = x - (c - dof) / dc if dc < 0.0 else 0.5 * (a + b)
            if not a < x_new < b:
                x_new = 0.5 * (a + b)
            if abs(x_new - x) < 1e-10 or b - a < 1e-10:
                x = x_new
                break
            x = x_new
        if a == a0 and chi2(a0)[0] <= dof:
            return float(lo)
        if b == b0 and chi2(b0)[0] >= dof:
            return float(hi)
        return float(np.exp(x))

    def exact(self) -> "JointProblem":
        """The same rows with the extrinsics (and the map) taken as exact: no calibration model
        (shares the arrays; what ``JointProblem([v.exact() for v in views], sigma)`` builds)."""
        out = object.__new__(JointProblem)
        out.__dict__.update(self.__dict__)
        out.views = [v.exact() for v in self.views]
        out.extrinsics_cov = out.extrinsics_factor = out.map_factor = out.cross_covariance = None
        return out

    def exact_step(self, T_base_map: np.ndarray, fit: JointFit, scale: float) -> Tuple[np.ndarray, JointFit, float]:
        """From ``fit`` (of the calibration-aware problem, at ``T_base_map``), the exact-extrinsics
        optimum as one Gauss-Newton step on the per-camera blocks it holds: the residuals, the
        Jacobian and the Huber weights do not depend on the extrinsics' uncertainty, only the
        normal equations do (their unmarginalised sum ``sum_c G_c``, ``sum_c b_c``). No residual is
        evaluated: they follow the step to first order, as the blocks ``b_c`` do (enough for
        the verdict of :func:`extrinsics_consistency`; the pose itself is solved from there).

        Returns (T_base_map of the exact problem, its fit (with the per-camera blocks ``G_cam``,
        ``b_cam`` and ``H_cam`` None, as :meth:`fit` of an exact problem would give, plus the blocks),
        the step's norm). Raises MeasurementError on singular normal equations."""
        if fit.G_cam is None or fit.b_cam is None:
            raise ValueError("exact_step needs a calibration model's fit")
        s2 = self.sigma ** 2
        H = fit.G_cam.sum(axis=0) / s2
        g = fit.b_cam.sum(axis=0) / s2
        try:
            delta = -_solve_spd(H, g)
        except np.linalg.LinAlgError:
            raise MeasurementError("joint estimator: singular normal equations (degenerate geometry)") from None
        r = fit.r + fit.J @ delta
        b_cam = fit.b_cam + fit.G_cam @ delta
        e2 = np.einsum("ni,ni->n", r, r)
        chi2 = float(fit.w @ e2) / s2
        # The Huber cost (_huber's): every corner within the scale, the usual case, from e2 directly.
        huber = 0.5 * float(e2.sum()) if e2.size and float(e2.max()) <= scale * scale else self._huber(r, scale)[0]
        out = JointFit(r, fit.J, fit.w, H, b_cam.sum(axis=0) / s2, chi2, huber, None, fit.G_cam, b_cam)
        return _perturb(T_base_map, delta), out, float(np.sqrt(delta @ delta))

    def with_sigma(self, sigma: float) -> "JointProblem":
        """The same problem with another pixel noise (shares the arrays)."""
        out = object.__new__(JointProblem)
        out.__dict__.update(self.__dict__)
        out.sigma = float(sigma)
        return out

    def map_covariance(self, fit: JointFit, T_base_map: np.ndarray) -> Optional[np.ndarray]:
        """(6, 6) covariance of the estimate's left perturbation due to the map's error, or None
        without a map model.

        The estimate does not weigh the map's error (its weights are the pixels' and the
        extrinsics'); it responds to it linearly: a residual change ``dr_c`` moves it by
        ``-H^-1 sum_c (I - G_c L_c M_c^-1 L_c^T) J_c^T D_c dr_c / sigma^2`` (the Woodbury form of
        ``J_c^T W_c``, ``M_c = sigma^2 I + L_c^T G_c L_c``), and marker m's pose error ``eps_m``
        (std: the map's position_std, rotation_std) changes its residuals by ``K_m eps_m`` with
        ``K_m = (d r / d X) F_m``. Markers' errors are taken as independent of each other (the
        map's stds say nothing of their correlation); a marker seen by several cameras moves all
        their residuals: the covariance is ``H^-1 (sum_m B_m B_m^T) H^-1`` with
        ``B_m = sum_c R_c J_cm^T D_cm K_cm / sigma^2`` over the cameras c that see marker m.
        """
        if self.map_factor is None or fit.G_cam is None:
            return None
        s2 = self.sigma ** 2
        J = fit.J
        Kq = np.matmul(np.matmul(J[:, :, 3:], T_base_map[:3, :3]), self.map_factor)      # (N, 2, 6)
        JtK = np.einsum("nia,nib->nab", J * fit.w[:, None, None], Kq)                    # (N, 6, 6)
        B = np.add.reduceat(JtK, np.arange(0, self.n, 4), axis=0)                        # per marker
        L = self.extrinsics_factor
        GL = fit.G_cam @ L
        M = s2 * np.eye(6) + np.transpose(L, (0, 2, 1)) @ GL
        Rc = np.eye(6) - GL @ _solve_spd_batch(M, np.transpose(L, (0, 2, 1)))           # (C, 6, 6)
        cam_of_marker = self.cam_index[::4]
        RB = np.matmul(Rc[cam_of_marker], B) / s2
        # A marker seen by several cameras moves all their residuals at once: its terms add first.
        _, which = np.unique(self.marker_ids, return_inverse=True)
        per_id = np.zeros((int(which.max()) + 1, 6, 6))
        np.add.at(per_id, which, RB)
        S = np.einsum("mab,mcb->ac", per_id, per_id)
        C = _spd_inverse(0.5 * (fit.H + fit.H.T))
        out = C @ S @ C
        return 0.5 * (out + out.T)

    def cost(self, T_base_map: np.ndarray, scale: float) -> float:
        """What the solver minimises at ``T_base_map``: the whitened chi^2 with a calibration
        model, else the Huber loss (threshold ``scale`` px) of the per-corner residual norms."""
        if self.extrinsics_cov is None:
            r, _ = self.residuals(T_base_map, jacobian=False)
            return self._huber(r, scale)[0]
        return self.fit(T_base_map, scale).cost

    def solve(self, T_base_map0: np.ndarray, scale: float, max_iterations: int = 8,
              tol: float = 1e-5, last_step: float = 1e-4) -> Tuple[np.ndarray, JointFit, int]:
        """Iteratively reweighted Gauss-Newton with a Huber loss (threshold ``scale`` px).

        A step that raises the cost is halved (up to 8 times). Stops when the step is below
        ``tol`` (rad / m) or after ``max_iterations``. A step below ``last_step`` is taken
        without evaluating the problem again (Gauss-Newton converges quadratically there: what
        it leaves is ~1e-8) and the residuals follow it to first order: one evaluation in three
        of a frame started from the prediction.

        Returns:
            (T_base_map, the :class:`JointFit` at it, iterations).
        """
        T = T_base_map0
        try:
            fit = self.fit(T, scale)
        except np.linalg.LinAlgError:
            raise MeasurementError("joint estimator: the start pose cannot be evaluated (the whitening's "
                                   "normal matrix is not positive definite)") from None
        it = 0
        for it in range(1, max_iterations + 1):
            try:
                delta = -_solve_spd(fit.H, fit.g)
            except np.linalg.LinAlgError:
                raise MeasurementError("joint estimator: singular normal equations (degenerate geometry)") from None
            norm = math.sqrt(delta @ delta)   # (math's: the same correctly rounded root, no ufunc call)
            if norm < tol:
                break  # converged: the step would change nothing measurable
            if norm < last_step and it > 1:
                T, fit = self.linear_step(T, fit, delta)
                break
            step = 1.0
            for _ in range(8):
                T_new = _perturb(T, step * delta)
                try:
                    fit_new = self.fit(T_new, scale)
                except np.linalg.LinAlgError:
                    # A trial pose so far off that the whitening's 6x6 systems lose positive
                    # definiteness in floating point (seen on a real recording, test_8: eigenvalues
                    # 0.04 .. 2e15): no descent there, a shorter step.
                    step *= 0.5
                    continue
                if fit_new.cost <= fit.cost or not np.isfinite(fit.cost):
                    break
                step *= 0.5
            else:
                break  # no descent: at the minimum to numerical precision
            T, fit = T_new, fit_new
        return T, fit, it

    @staticmethod
    def linear_step(T_base_map: np.ndarray, fit: JointFit, delta: np.ndarray) -> Tuple[np.ndarray, JointFit]:
        """``T_base_map`` moved by ``delta`` with the residuals (and the per-camera gradients) of
        ``fit`` following to first order, the normal equations kept: for a step so small that
        evaluating the problem again would change nothing measurable (~1e-8)."""
        b_cam = None if fit.b_cam is None else fit.b_cam + fit.G_cam @ delta
        return _perturb(T_base_map, delta), JointFit(fit.r + np.einsum("nia,a->ni", fit.J, delta), fit.J, fit.w,
                                                     fit.H, fit.g * 0.0, fit.chi2, fit.cost, fit.H_cam, fit.G_cam,
                                                     b_cam, fit.spectrum)

    def covariance(self, fit: JointFit) -> np.ndarray:
        """(6, 6) covariance of the left perturbation of ``T_base_map`` (whitened units: multiply
        by a variance factor when the residuals say the noise is larger).

        ``H^-1``, plus, with a ``cross_covariance`` C between cameras' extrinsic errors, the
        sandwich term ``H^-1 (sum_{c != d} H_c C_cd H_d) H^-1`` (the estimate is linear in the
        extrinsic errors: ``H^-1 sum_c H_c eta_c``, since J_c carries eta_c like a pose motion).

        The views' common error (``shared_factor`` F_c: free-running cameras moved to the frame's
        stamp with one velocity estimate, whose error moves camera c by ``dt_c`` times it) is such
        a cross covariance, ``C_cd = F_c F_d^T``: its term is
        ``H^-1 (P P^T - sum_c P_c P_c^T) H^-1`` with ``P_c = H_c F_c``, ``P = sum_c P_c``. The
        weights take each camera's whole displacement error as its own (``extrinsics_cov``
        includes ``F_c F_c^T``), which is what the diagonal ``H^-1`` accounts for; without the
        cross terms the estimate's covariance would count the one velocity error as C
        independent ones, averaged away.
        """
        C = _spd_inverse(0.5 * (fit.H + fit.H.T))
        if fit.H_cam is not None and (self.cross_covariance is not None or self.shared_factor is not None):
            S = np.zeros((6, 6))
            if self.cross_covariance is not None:
                Hc = np.concatenate(list(fit.H_cam), axis=1)  # (6, 6C)
                S = S + Hc @ self.cross_covariance @ Hc.T
            if self.shared_factor is not None:
                P = fit.H_cam @ self.shared_factor             # (C, 6, k)
                Ps = P.sum(axis=0)
                S = S + Ps @ Ps.T - np.einsum("cak,cbk->ab", P, P)
            C = C + C @ S @ C
        return 0.5 * (C + C.T)

    def shared_gain(self, fit: JointFit) -> Optional[np.ndarray]:
        """(6, k) ``K = H^-1 sum_c H_c F_c``: the estimate's error from the views' common error z
        (``shared_factor``), whose part of :meth:`covariance` is ``K K^T``; None without one."""
        if self.shared_factor is None or fit.H_cam is None:
            return None
        return _shared_gain(fit.H, fit.H_cam, self.shared_factor)


def _shared_gain(H: np.ndarray, H_cam: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(6, k) ``H^-1 sum_c H_c F_c``: a pose estimate's response to the views' common error
    (:meth:`JointProblem.shared_gain`; with the exact problem's blocks, the exact pose's)."""
    return _spd_inverse(0.5 * (H + H.T)) @ np.einsum("cab,cbk->ak", H_cam, F)


def marker_map_factor(T_map_marker: np.ndarray, corners: np.ndarray, position_std: np.ndarray,
                      rotation_std: np.ndarray) -> np.ndarray:
    """(4, 3, 6) per corner ``F`` with ``F F^T`` the covariance of its map position when the
    marker's pose is off by ``position_std`` (m, along the map axes) and ``rotation_std`` (rad,
    about the marker's own axes), the map file's convention: ``dX = dp + (R_map_marker dθ) x
    (X - centre)``, so ``F = [I, -[X - centre]x R_map_marker] diag(std)``."""
    R = T_map_marker[:3, :3]
    c = T_map_marker[:3, 3]
    std = np.concatenate([np.asarray(position_std, dtype=np.float64), np.asarray(rotation_std, dtype=np.float64)])
    out = np.zeros((corners.shape[0], 3, 6))
    for i, X in enumerate(corners):
        out[i, :, :3] = np.eye(3)
        out[i, :, 3:] = -geo.skew(X - c) @ R
    return out * std[None, None, :]


def jitter_covariance(T_base_cam: np.ndarray, rot_std: float, trans_std: float) -> np.ndarray:
    """(6, 6) covariance, as a left perturbation (w, v) of ``T_base_cam`` in the base frame, of a
    camera whose extrinsics jitter by ``rot_std`` (rad) and ``trans_std`` (m) per axis of its own
    optical frame (``T_base_cam_true = T_base_cam · D``, the simulator's ring vibration): the same
    convention as the ring file's ``extrinsics_std`` (:attr:`RingCamera.extrinsics_covariance`).
    Independent from frame to frame, it adds to the calibration's covariance, which is fixed."""
    A = geo.se3_adjoint(np.asarray(T_base_cam, dtype=np.float64))
    return A @ np.diag([rot_std ** 2] * 3 + [trans_std ** 2] * 3) @ A.T


def _solve_spd_batch(M: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``M_c^-1 B_c`` for (C, n, n) symmetric positive-definite ``M`` and (C, n, k) ``B``
    (LAPACK posv per matrix, as :func:`_spd_inverse`: numpy's batched solve costs ~150 us of CPU
    for eight 6x6 systems with OpenBLAS's threads, this ~3 us each). Raises LinAlgError."""
    out = np.empty(B.shape)
    for c in range(M.shape[0]):
        _, x, info = _lapack.dposv(M[c], B[c], lower=False)
        if info != 0:
            raise np.linalg.LinAlgError("matrix is not positive definite")
        out[c] = x
    return out


def _solve_spd(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(n,) ``H^-1 g`` for one symmetric positive-definite ``H``: :func:`_solve_spd_batch` of a single
    system (the same LAPACK call) without the batch's arrays. Raises LinAlgError."""
    _, x, info = _lapack.dposv(H, g[:, None], lower=False)
    if info != 0:
        raise np.linalg.LinAlgError("matrix is not positive definite")
    return x[:, 0]


def _psd_factor(S: np.ndarray) -> np.ndarray:
    """(6, 6) ``L`` with ``L L^T = S`` for a positive semi-definite ``S`` (zero for an exact camera)."""
    lam, V = np.linalg.eigh(0.5 * (S + S.T))
    return V * np.sqrt(np.clip(lam, 0.0, None))


def _spd_inverse(H: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric positive-definite matrix (LAPACK potrf + potri).

    Why not ``np.linalg.inv``: for a 6x6 matrix OpenBLAS's multi-threaded getri path costs 20 us
    on an idle machine and over 1 ms when the cores are busy (thread hand-off); the Cholesky
    route stays near 10-30 us. Raises LinAlgError when H is not positive definite.
    """
    c, info = _lapack.dpotrf(H, lower=False)
    if info != 0:
        raise np.linalg.LinAlgError("matrix is not positive definite")
    inv, info = _lapack.dpotri(c, lower=False)
    if info != 0:
        raise np.linalg.LinAlgError("matrix is singular")
    # The upper triangle mirrored: np.triu(inv) + np.triu(inv, 1).T (the same numbers, + 0.0 as
    # there turning a -0.0 into 0.0) without its two masks built per call (~12 us of 16 for 6x6).
    n = inv.shape[0]
    upper = _UPPER.get(n)
    if upper is None:
        upper = _UPPER[n] = ~np.tri(n, k=-1, dtype=bool)
    return np.where(upper, inv, inv.T) + 0.0


#: n -> (n, n) bool, True on and above the diagonal (:func:`_spd_inverse`)
_UPPER: Dict[int, np.ndarray] = {}


def covariance_from_information(H: np.ndarray, sigma_px: float, T_map_base: np.ndarray) -> np.ndarray:
    """6x6 covariance over (x, y, z, rx, ry, rz) in the map frame from the information ``H``.

    ``H`` is over the left perturbation ``delta = (w, v)`` of ``T_base_map``; since
    ``T_map_base' = T_map_base · exp(-delta)``, the map-frame position moves by ``-R v`` and the
    orientation by the world rotation vector ``-R w`` (R = rotation of ``T_map_base``), so
    ``Cov = G (sigma^2 H^-1) G^T`` with ``G = [[0, -R], [-R, 0]]``.
    """
    try:
        C = _spd_inverse(0.5 * (H + H.T)) * sigma_px ** 2
    except np.linalg.LinAlgError:
        raise MeasurementError("covariance: singular information matrix") from None
    return map_frame_covariance(C, T_map_base)


def map_frame_covariance(C: np.ndarray, T_map_base: np.ndarray) -> np.ndarray:
    """The (w, v) covariance ``C`` of the left perturbation of ``T_base_map`` as 6x6 over
    (x, y, z, rx, ry, rz) in the map frame (see :func:`covariance_from_information`)."""
    R = T_map_base[:3, :3]
    G = np.zeros((6, 6))
    G[:3, 3:] = -R
    G[3:, :3] = -R
    cov = G @ C @ G.T
    return 0.5 * (cov + cov.T)


def crlb_covariance(T_map_base: np.ndarray, blocks: Sequence[Tuple[np.ndarray, CameraModel, np.ndarray]],
                    sigma_px: float, eps: float = 1e-6) -> np.ndarray:
    """Cramér-Rao bound of the robot pose for a given geometry and pixel noise.

    Args:
        T_map_base: (4, 4) true robot pose.
        blocks: per camera ``(T_cam_base, model, map points (N, 3))`` — the corners it sees.
        sigma_px: 1-sigma i.i.d. Gaussian noise per pixel coordinate.

    Returns:
        6x6 bound over (x, y, z, rx, ry, rz) in the map frame: ``inv(J^T J / sigma^2)`` with J
        the Jacobian of the *exact* projection (full distortion model), taken by central
        differences at the true pose — independent of the estimator's own analytic Jacobian.
    """
    T_base_map = geo.inverse(T_map_base)
    rows = []
    for T_cam_base, model, pts in blocks:
        def proj(T_bm):
            return model.project(geo.transform_points(T_cam_base @ T_bm, pts)).ravel()
        cols = []
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            cols.append((proj(geo.se3_perturb(T_base_map, d)) - proj(geo.se3_perturb(T_base_map, -d))) / (2 * eps))
        rows.append(np.stack(cols, axis=1))
    J = np.concatenate(rows)
    return covariance_from_information(J.T @ J, sigma_px, T_map_base)


# --- the localizer --------------------------------------------------------------------------

@dataclass
class _JointSolution:
    problem: JointProblem
    T_base_map: np.ndarray
    fit: JointFit
    iterations: int
    rms: float
    covariance: np.ndarray    # (6, 6) of the left perturbation of T_base_map
    outliers: int = 0
    pixel_noise: float = float("nan")   # measured from the residuals (estimate_pixel_noise), px
    #: (6, k) the pose error's response to the views' common error z (``covariance`` holds
    #: ``shared_gain shared_gain^T``), or None: :meth:`JointProblem.shared_gain`.
    shared_gain: Optional[np.ndarray] = None

    @property
    def chi2(self) -> float:
        """The whitened chi^2 at the problem's pixel noise (``pixel_noise``: the units of
        ``ambiguity_chi2``). A solution solved at the measured noise holds its fit at that noise
        (its blocks and residuals are what the later steps read): refitted here, when compared."""
        if np.isfinite(self.pixel_noise) and self.fit.G_cam is not None:
            return self.problem.refit(self.fit).chi2
        return self.fit.chi2

    @property
    def r(self) -> np.ndarray:
        return self.fit.r

    @property
    def J(self) -> np.ndarray:
        return self.fit.J


def extrinsics_consistency(problem: JointProblem, fit: JointFit) -> Optional[Tuple[float, int, int]]:
    """Whether a frame's cameras agree through the extrinsics: ``(F, d1, d2)`` at ``fit`` (the
    optimum of ``problem`` with the extrinsics taken as exact), or None when it cannot be told
    (one camera, or no residual degrees of freedom within the cameras).

    Per camera c, with its (Huber-weighted) normal equations ``G_c = J_c^T D J_c`` and
    ``b_c = J_c^T D r_c``, its own pose would lower the squared residuals by ``b_c^T G_c^+ b_c``
    (Gauss-Newton). ``D = sum_c`` of those (``d1 = 6(C-1)`` degrees of freedom: the joint optimum
    already balances the cameras' gradients), ``S = sum_c r_c^T D r_c - D`` (``d2 = 2N - 6C``);
    ``F = (D / d1) / (S / d2)``: F-distributed when the extrinsics are exact, whatever the pixel
    noise (it cancels)."""
    C = len(problem.views)
    d1, d2 = 6 * (C - 1), 2 * problem.n - 6 * C
    if C < 2 or d2 < 1:
        return None
    if fit.G_cam is not None and fit.b_cam is not None:
        # The per-camera blocks are in the fit already (JointProblem.exact_step): only q is summed.
        G, b = fit.G_cam, fit.b_cam
        q = np.add.reduceat(fit.weighted_squares(), problem.offsets[:-1])
    else:
        rr = np.where(np.isfinite(fit.r), fit.r, 0.0)
        Ja = np.concatenate([fit.J, rr[:, :, None]], axis=2)
        A7 = np.add.reduceat(np.einsum("nia,nib->nab", Ja * fit.w[:, None, None], Ja), problem.offsets[:-1],
                             axis=0)
        G, b, q = A7[:, :6, :6], A7[:, :6, 6], A7[:, 6, 6]
    D = _sum_pinv_quadratic(G, b)
    S = float(np.sum(q)) - D
    if not (S > 0.0 and np.isfinite(D)):
        return None
    return (D / d1) / (S / d2), d1, d2


def _sum_pinv_quadratic(G: np.ndarray, b: np.ndarray) -> float:
    """``sum_c b_c^T G_c^+ b_c`` for (C, 6, 6) symmetric positive semi-definite ``G`` and (C, 6) ``b``.

    Blocks well conditioned (every Cholesky pivot above 1e-10 of the largest diagonal entry, the
    usual frame) go through one batched Cholesky factorisation and triangular solve, ~15 us for 8
    cameras; otherwise one batched eigh with np.linalg.pinv's rule (eigenvalues within 1e-15 of
    the largest count as zero), ~60 us. On well-conditioned blocks the two agree to rounding (b lies
    in the range of J^T, so a nearly null direction of G carries nearly nothing of b either)."""
    try:
        K = np.linalg.cholesky(G)
        piv = K[:, _I6, _I6]
        if piv.size and float((piv * piv).min()) > 1e-10 * float(G[:, _I6, _I6].max()):
            z = np.linalg.solve(K, b[:, :, None])
            return float(np.sum(z * z))
    except np.linalg.LinAlgError:
        pass
    lam, U = np.linalg.eigh(G)
    ub = np.matmul(b[:, None, :], U)[:, 0, :]
    keep = np.abs(lam) > 1e-15 * np.abs(lam).max(axis=1, keepdims=True)
    return float(np.sum(np.where(keep, ub * ub / np.where(keep, lam, 1.0), 0.0)))


_F_CACHE: Dict[Tuple[float, int, int], float] = {}


def _f_quantile(prob: float, d1: int, d2: int) -> float:
    """The ``prob`` quantile of the F(d1, d2) distribution (cached: a few (d1, d2) per ring)."""
    key = (prob, d1, d2)
    q = _F_CACHE.get(key)
    if q is None:
        from scipy.stats import f as f_dist

        q = _F_CACHE[key] = float(f_dist.ppf(prob, d1, d2))
    return q


def camera_blocks(problem: JointProblem, fit: JointFit) -> Tuple[np.ndarray, np.ndarray]:
    """Per camera ``G_c = J_c^T D_c J_c`` (C, 6, 6) and ``b_c = J_c^T D_c r_c`` (C, 6) of ``fit``
    (px units, not whitened): the blocks ``fit`` holds when it has them, else summed from its rows."""
    if fit.G_cam is not None and fit.b_cam is not None:
        return fit.G_cam, fit.b_cam
    rr = np.where(np.isfinite(fit.r), fit.r, 0.0)
    Jw = fit.J * fit.w[:, None, None]
    G = np.add.reduceat(np.einsum("nia,nib->nab", Jw, fit.J), problem.offsets[:-1], axis=0)
    b = np.add.reduceat(np.einsum("nia,ni->na", Jw, rr), problem.offsets[:-1], axis=0)
    return G, b


class _PersistenceCamera:
    """One camera's frames in :class:`CalibrationPersistence`'s window: rows ``lo:hi`` of the
    buffers, the oldest first."""

    def __init__(self, capacity: int):
        self.serial: List[int] = []
        self.ids: List[List[int]] = []   # each frame's marker ids
        self.seen: Dict[int, List[int]] = {}   # marker id -> the serials of the frames that saw it
        self.G = np.empty((capacity, 6, 6))
        self.b = np.empty((capacity, 6))
        self.disjoint = np.zeros((capacity, capacity), dtype=bool)
        self.lo = self.hi = 0

    def append(self, serial: int, ids: Sequence[int], G: np.ndarray, b: np.ndarray) -> None:
        ids = [int(i) for i in ids]
        shared = set()   # the window's frames that saw one of these markers
        for i in ids:
            frames = self.seen.setdefault(i, [])
            shared.update(frames)
            frames.append(serial)
        if self.hi == len(self.b):   # full: the window's rows to the start
            lo, hi = self.lo, self.hi
            n = hi - lo
            self.G[:n], self.b[:n] = self.G[lo:hi], self.b[lo:hi]
            self.disjoint[:n, :n] = self.disjoint[lo:hi, lo:hi]
            self.lo, self.hi = 0, n
        lo, k = self.lo, self.hi
        row = np.array([s not in shared for s in self.serial] + [False], dtype=bool)
        self.disjoint[k, lo:k + 1] = row
        self.disjoint[lo:k + 1, k] = row
        self.G[k] = G
        self.b[k] = b
        self.hi = k + 1
        self.serial.append(serial)
        self.ids.append(ids)

    def drop_until(self, oldest: int) -> None:
        """Forget the frames of serials up to ``oldest``: the oldest first, as in each marker's list
        of serials."""
        while self.serial and self.serial[0] <= oldest:
            serial = self.serial.pop(0)
            for i in set(self.ids.pop(0)):
                frames = self.seen[i]
                while frames and frames[0] == serial:   # twice: the frame listed the marker twice
                    del frames[0]
                if not frames:
                    del self.seen[i]
            self.lo += 1


@functools.lru_cache(maxsize=None)
def _strict_upper(n: int) -> np.ndarray:
    """(n, n) read-only mask of the pairs i < j (:meth:`CalibrationPersistence.correlation`: np.tri
    built it on every frame the window is updated, ~30 us; n is at most the window's length)."""
    mask = ~np.tri(n, dtype=bool)
    mask.flags.writeable = False
    return mask


class CalibrationPersistence:
    """Whether the cameras' disagreement through the extrinsics is a calibration error: over the
    last ``window`` multi-camera frames, does it follow the cameras from one marker to another?

    At the exact-extrinsics optimum of a frame, camera c's own pose correction is
    ``G_c^+ b_c`` (:func:`extrinsics_consistency` sums ``b_c^T G_c^+ b_c`` over the cameras). An
    error of camera c's extrinsics ``eta_c`` (constant, in the base frame) makes ``b_c ~ G_c eta_c``
    in every frame, whatever the camera sees; an error of the map or of a tag's detection moves the
    correction of the frames that see that marker, and noise none twice. So the rule correlates
    each camera's ``b_c`` between the window's frames in which it sees *no common marker*:

        rho = sum_pairs b_f^T A^+ b_g / sum_pairs sqrt(b_f^T A^+ b_f  b_g^T A^+ b_g)

    (``A = sum_f G_f`` of that camera over the window: the metric of its information; the pairs
    of all cameras pooled): about 1 when a constant extrinsic error dominates the disagreement, 0
    when nothing about the camera repeats (a positive-definite metric: ``rho`` is a weighted
    average of the pairs' cosines). The common part of all cameras' errors moves the rig's pose
    and no camera's correction: neither this nor the F-test sees it.

    :meth:`add` records a frame; :meth:`correlation` gives ``(rho, pairs)``, ``pairs`` the frame
    pairs it pooled (0: nothing to tell: each camera saw the same markers all along)."""

    def __init__(self, window: int):
        self.window = int(window)
        self._serial = 0   # frames added
        # Per camera, its frames in the window (the oldest first): serials, marker ids (a marker ->
        # the serials that saw it) and, in rows lo:hi of buffers of 2 (window + 1) rows, G_c, b_c
        # and which pairs of its frames saw no common marker (symmetric, a row and column per
        # frame). A frame leaving the window moves lo; the rows are moved to the buffers' start only
        # when hi reaches their end, so each frame is copied about once (issue 16: re-concatenating
        # the window every frame cost ~0.3 ms).
        self._cams: Dict[str, _PersistenceCamera] = {}

    def __len__(self) -> int:
        return min(self._serial, self.window)

    def clear(self) -> None:
        self._serial = 0
        self._cams = {}

    def add(self, names: Sequence[str], ids: Sequence[Sequence[int]], G: np.ndarray, b: np.ndarray) -> None:
        """One frame's cameras, their marker ids and blocks ``G_c`` (C, 6, 6), ``b_c`` (C, 6) at the
        exact-extrinsics optimum (:func:`camera_blocks`)."""
        if self.window <= 0:
            return
        self._serial += 1
        oldest = self._serial - self.window   # serials up to this have left the window
        for name, m, Gc, bc in zip(names, ids, G, b):
            cam = self._cams.get(name)
            if cam is None:
                cam = self._cams[name] = _PersistenceCamera(2 * (self.window + 1))
            cam.append(self._serial, m, Gc, bc)
        for name in list(self._cams):
            cam = self._cams[name]
            cam.drop_until(oldest)
            if not cam.serial:
                del self._cams[name]

    def correlation(self) -> Tuple[float, int]:
        cams = [c for c in self._cams.values() if len(c.serial) > 1]
        if not cams:
            return float("nan"), 0
        # The cameras side by side (padded to the longest): one batched decomposition and product.
        n = max(len(c.serial) for c in cams)
        B = np.zeros((len(cams), n, 6))
        ok = np.zeros((len(cams), n, n), dtype=bool)
        A = np.empty((len(cams), 6, 6))
        for k, c in enumerate(cams):
            m, lo, hi = len(c.serial), c.lo, c.hi
            B[k, :m] = c.b[lo:hi]
            ok[k, :m, :m] = c.disjoint[lo:hi, lo:hi]
            A[k] = c.G[lo:hi].sum(axis=0)
        ok &= _strict_upper(n)   # the pairs i < j (np.triu(ok, 1), without its copies)
        pairs = int(ok.sum())
        if not pairs:
            return float("nan"), 0
        lam, U = np.linalg.eigh(A)
        keep = lam > 1e-12 * np.maximum(lam.max(axis=1, keepdims=True), 1e-300)
        scale = np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)
        Y = np.matmul(B, U * scale[:, None, :])          # b^T A^+ b' = y . y'
        K = np.matmul(Y, np.transpose(Y, (0, 2, 1)))
        d = np.sqrt(np.maximum(np.einsum("cii->ci", K), 0.0))
        num = float(K[ok].sum())
        den = float((d[:, :, None] * d[:, None, :])[ok].sum())
        if not den > 0.0:
            return float("nan"), 0
        return num / den, pairs


class VibrationEstimate:
    """How much the cameras really jitter from frame to frame against the ring, measured from the
    data over the last ``window`` multi-camera frames (:class:`CalibrationPersistence`'s window).

    The declared vibration (``extrinsic_jitter_deg`` / ``_m``: camera c's per-frame extrinsic
    error ``eta_c``, covariance ``V_c`` in the base frame, :func:`jitter_covariance`) is scaled by
    ``kappa^2`` (``V_c -> kappa^2 V_c``), and ``kappa^2`` is what the data tell. At a frame's
    exact-extrinsics optimum camera c's gradient is ``b_c = J_c^T D r_c`` (:func:`camera_blocks`);
    with the pose's own response removed (``H = sum_d G_d``, ``K_d = H^-1 G_d``)

        b_c = G_c (eta_c - sum_d K_d eta_d) + (pixel noise) + (what persists)

    The pixel noise gives ``b_c`` the covariance ``N_c = s^2 (G_c - G_c H^-1 G_c)``, ``s^2 = S / d2``
    the frame's noise within the cameras (:func:`extrinsics_consistency`'s denominator: what no
    extrinsic error touches), the vibration ``kappa^2 M_c`` with
    ``M_c = G_c (V_c - K_c V_c - V_c K_c^T + sum_d K_d V_d K_d^T) G_c``. What persists (the
    calibration's error, the map's, a tag's detection bias, a lens model's error) is removed by
    pairing each camera's frame with its previous one when it saw the same markers in the
    multi-camera frame just before (each frame in one pair at most, so the pairs are independent):
    ``d = b_f - b_g`` has the covariance ``N_f + N_g + kappa^2 (M_f + M_g)``. With the weight
    ``W = (N_f + N_g + M_f + M_g)^-1`` (the declared vibration) every pair gives
    ``t = d^T W d - tr(W (N_f + N_g))`` and ``m = tr(W (M_f + M_g))``, ``E[t] = kappa^2 m``, and the
    window pools them (a moment estimate, unbiased):

        kappa^2 = sum t / sum m,   its standard error  sqrt(sum (t - kappa^2 m)^2) / sum m

    :meth:`add` records a frame, :meth:`estimate` gives ``(kappa^2, standard error, pairs)``."""

    def __init__(self, window: int):
        self.window = int(window)
        self._serial = 0
        #: camera -> (serial, marker ids, its frame's record, its index there) of its last frame
        #: not yet paired.
        self._last: Dict[str, tuple] = {}
        #: (serial, t, m) of the window's pairs, the oldest first, and their running sums of t, m,
        #: t^2, t m and m^2.
        self._pairs: Deque[Tuple[int, float, float]] = collections.deque()
        self._sums = [0.0] * 5

    def clear(self) -> None:
        self._serial = 0
        self._last = {}
        self._pairs = collections.deque()
        self._sums = [0.0] * 5

    def add(self, names: Sequence[str], ids: Sequence[Sequence[int]], G: np.ndarray, b: np.ndarray,
            noise: Union[float, Callable[[], float]], V: Sequence[np.ndarray]) -> None:
        """One frame: its cameras, their marker ids, blocks ``G_c`` (C, 6, 6) and ``b_c`` (C, 6) at
        the exact-extrinsics optimum, the pixel noise variance within the cameras ``s^2`` (px^2; or
        a function giving it, called only when one of the frame's cameras pairs) and each camera's
        declared vibration covariance ``V_c`` (6, 6). The terms of a frame are computed only when
        one of its cameras pairs (each frame at most once)."""
        if self.window <= 0:
            return
        self._serial += 1
        oldest = self._serial - self.window
        while self._pairs and self._pairs[0][0] <= oldest:
            _, t, m = self._pairs.popleft()
            self._sums = [a - x for a, x in zip(self._sums, (t, m, t * t, t * m, m * m))]
        if not self._pairs:
            self._sums = [0.0] * 5   # no rounding left over
        last, self._last = self._last, {}
        if len(names) < 2:
            return
        frame = [G, b, noise, V, None]   # None: its terms (N, M) not computed yet
        matched = []
        for c, (n, m) in enumerate(zip(names, ids)):
            key = tuple(m)
            q = last.get(n)
            if q is not None and q[0] == self._serial - 1 and q[1] == key:
                matched.append((c, q[2], q[3]))   # each frame in one pair at most: not kept
            else:
                self._last[n] = (self._serial, key, frame, c)
        if not matched:
            return
        one = self._frame_terms(frame)
        two = self._frame_terms(matched[0][1])   # the frame just before: every pair's other frame
        if one is None or two is None:
            return
        c = [k for k, _, _ in matched]
        k = [j for _, _, j in matched]
        d = np.asarray(b, dtype=np.float64)[c] - np.asarray(matched[0][1][1], dtype=np.float64)[k]
        Mm = one[1][c] + two[1][k]
        S = one[0][c] + two[0][k] + Mm
        try:
            X = _solve_spd_batch(0.5 * (S + np.transpose(S, (0, 2, 1))), np.concatenate([d[:, :, None], Mm], axis=2))
        except np.linalg.LinAlgError:
            return
        # tr(W N) = 6 - tr(W M): W = (N + M)^-1.
        m = X[:, _I6, _I6 + 1].sum(axis=1)
        t = (d * X[:, :, 0]).sum(axis=1) - (6.0 - m)
        for tk, mk in zip(t.tolist(), m.tolist()):
            if mk > 0.0:
                self._pairs.append((self._serial, tk, mk))
                self._sums = [a + x for a, x in zip(self._sums, (tk, mk, tk * tk, tk * mk, mk * mk))]

    @staticmethod
    def _frame_terms(frame: list) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """``(N, M)`` (C, 6, 6) of every camera of ``frame`` (:meth:`add`'s record), computed once,
        or None when the frame's noise or normal equations are unusable."""
        if frame[4] is None:
            G, _, noise, V, _ = frame
            frame[4] = False
            noise = float(noise() if callable(noise) else noise)
            if noise > 0.0 and np.isfinite(noise):
                G = np.asarray(G, dtype=np.float64)
                V = np.asarray(V, dtype=np.float64)
                C = G.shape[0]
                _, X, info = _lapack.dposv(G.sum(axis=0), np.transpose(G, (1, 0, 2)).reshape(6, 6 * C), lower=False)
                if info == 0:
                    K = np.transpose(X.reshape(6, C, 6), (1, 0, 2))   # K_d = H^-1 G_d
                    KV = np.matmul(K, V)
                    Q = np.matmul(KV, np.transpose(K, (0, 2, 1))).sum(axis=0)   # sum_d K_d V_d K_d^T
                    inner = V - KV - np.transpose(KV, (0, 2, 1)) + Q
                    frame[4] = (noise * (G - np.matmul(G, K)), np.matmul(np.matmul(G, inner), G))
        return frame[4] or None

    def estimate(self) -> Tuple[float, float, int]:
        """``(kappa^2, its standard error, pairs)`` over the window (nan, nan, 0: no pair)."""
        if not self._pairs:
            return float("nan"), float("nan"), 0
        st, sm, stt, stm, smm = self._sums
        if not sm > 0.0:
            return float("nan"), float("nan"), 0
        k2 = st / sm
        # sum (t - k2 m)^2 from the running sums (rounding can leave it a hair below 0)
        return k2, float(np.sqrt(max(stt - 2.0 * k2 * stm + k2 * k2 * smm, 0.0))) / sm, len(self._pairs)


class RingLocalizer:
    """Robot pose from ring frames against a marker map.

    Args:
        ring: the calibrated ring (intrinsics fall back to it; extrinsics ``T_base_cam``).
        marker_map: the map; its frame is the output frame.
        params: :class:`LocalizationParams`.

    ``process`` costs O(markers in view): the map is only accessed by id.
    """

    def __init__(self, ring: CameraRing, marker_map: MarkerMap, params: Optional[LocalizationParams] = None):
        self.params = params or LocalizationParams()
        self.marker_map = marker_map
        self._axes_cache: Dict[int, np.ndarray] = {}
        self._map_factor_cache: Dict[int, object] = {}   # id -> (4, 3, 6) factor, or False: exact
        #: the ids of one view (in order) -> their stacked factors or None (:meth:`_map_factor`): a
        #: camera sees the same markers frame after frame. Cleared with the per-id cache.
        self._view_factor_cache: Dict[Tuple[int, ...], Optional[np.ndarray]] = {}
        #: px: the pixel noise the joint estimate is solved at (``estimate_pixel_noise``): the noise
        #: measured in the last frame posed by the joint estimator, ``pixel_noise`` before it.
        self.pixel_noise_guess = float(self.params.pixel_noise)
        #: name -> :class:`CameraView` of the last frame processed (the moved-marker check reuses
        #: its corners: :meth:`marker_check.MarkerCheck.update`).
        self.last_views: Dict[str, CameraView] = {}
        #: (rho, pairs) of the window after the last multi-camera frame (:class:`CalibrationPersistence`).
        self.last_persistence: Tuple[float, int] = (float("nan"), 0)
        #: (kappa^2, its standard error, pairs) of the window's vibration estimate after the last
        #: multi-camera frame (:class:`VibrationEstimate`; kappa: the jitter over the declared one).
        self.last_vibration: Tuple[float, float, int] = (float("nan"), float("nan"), 0)
        #: ((camera, marker ids) of the views, frames it was reused, the robot's position in the map
        #: and T_base_map's rotation) of the last clearly inconsistent frame (:meth:`_exact_if_consistent`),
        #: or None.
        self._verdict: Optional[tuple] = None
        self.set_ring(ring)

    def set_ring(self, ring: CameraRing) -> None:
        """Use new extrinsics/intrinsics (e.g. from tf), and their uncertainty.

        The uncertainty of a camera's extrinsics (``fusion: joint``) is the covariance the map
        stores for its refined extrinsics (``ring_calibration.covariance``, the mapping bundle
        adjustment's, with the correlations between cameras) when the extrinsics in force are
        those (ring_tf publishes them given the map file), else the ring file's
        ``extrinsics_std``. ``fusion: joint_exact_extrinsics`` takes them as exact.
        """
        # The window's evidence is about the extrinsics in force: kept while they stay the same
        # (tf may hand the same ring again), else started anew.
        before = getattr(self, "_T_base_cam", None)
        if before is None or set(before) != set(ring.names) or not all(
                _same_pose(before[c.name], c.T_base_cam) for c in ring.cameras):
            self.persistence = CalibrationPersistence(self.params.persistence_window)
            #: The window's verdict after the last multi-camera frame: the ring's calibration is borne
            #: out by the data (:meth:`_window_update`); the next frames are solved without its
            #: uncertainty, the vibration's only.
            self._calibration_cleared = False
            #: The cameras' per-frame jitter measured over the same window (estimate_vibration), and
            #: the scale (kappa^2, at most 1) of the declared vibration the frames are solved with.
            self.vibration = VibrationEstimate(self.params.persistence_window)
            self.vibration_scale = 1.0
        #: Cameras the ring declares non-rigid (``wiggle``): the window never clears their frames.
        self._wiggling = {c.name for c in ring.cameras if c.wiggle is not None}
        self.ring = ring
        self._verdict = None   # new extrinsics or their uncertainty: the consistency is tested again
        #: camera names -> (:meth:`_cross_covariance` of views of those cameras,), for this ring.
        self._cross_cache: Dict[Tuple[str, ...], tuple] = {}
        self._T_cam_base = {c.name: c.T_cam_base for c in ring.cameras}
        self._T_base_cam = {c.name: np.asarray(c.T_base_cam, dtype=np.float64) for c in ring.cameras}
        self._ext_cov: Dict[str, Optional[np.ndarray]] = {c.name: None for c in ring.cameras}
        self._ext_factor: Dict[str, Optional[np.ndarray]] = {c.name: None for c in ring.cameras}
        self._ext_full: Optional[np.ndarray] = None    # (6n, 6n) base-frame, cameras in _ext_index
        self._ext_index: Dict[str, int] = {}
        self.extrinsics_source: Dict[str, str] = {c.name: "exact" for c in ring.cameras}
        self._ext_factor_any = False
        self._vib_cov: Dict[str, Optional[np.ndarray]] = dict(self._ext_cov)
        self._cal_cov: Dict[str, Optional[np.ndarray]] = dict(self._ext_cov)
        self._vib_factor: Dict[str, Optional[np.ndarray]] = dict(self._ext_factor)
        if self.params.fusion != "joint":
            return
        for c in ring.cameras:
            self._ext_cov[c.name] = c.extrinsics_covariance
            self.extrinsics_source[c.name] = "ring file"
        self._use_map_covariance(ring)
        # The ring file's calibration alone (declared, a guess: the window's verdict may leave it out;
        # the map's covariance of its refined extrinsics is the mapping's estimate, and stays).
        # A ring file declaring its calibration exact (std 0) has nothing to clear.
        self._cal_cov = {n: C if self.extrinsics_source[n] == "ring file" and C is not None and np.any(C) else None
                         for n, C in self._ext_cov.items()}
        p = self.params
        #: The declared vibration per camera (estimator/extrinsic_jitter_*), and each camera's
        #: calibration covariance without it.
        self._vib_declared = {c.name: jitter_covariance(self._T_base_cam[c.name], np.radians(p.extrinsic_jitter_deg),
                                                        p.extrinsic_jitter_m) for c in ring.cameras}
        self._base_cov = dict(self._ext_cov)
        self._apply_vibration(self.vibration_scale)

    def _apply_vibration(self, scale: float) -> None:
        """The noise model's covariances with the declared vibration scaled by ``scale`` (kappa^2,
        :class:`VibrationEstimate`; 1: as declared)."""
        self.vibration_scale = float(scale)
        declared = self.params.extrinsic_jitter_deg > 0 or self.params.extrinsic_jitter_m > 0
        vib = {n: V * self.vibration_scale for n, V in self._vib_declared.items()}
        # The ring's vibration: independent per camera and frame (no cross terms).
        self._ext_cov = {n: self._base_cov[n] + vib[n] for n in self._base_cov}
        self._ext_factor = {n: None if C is None else _psd_factor(C) for n, C in self._ext_cov.items()}
        self._ext_factor_any = any(F is not None for F in self._ext_factor.values())
        # The vibration alone (what a frame is solved with once the window cleared the calibration).
        self._vib_cov = {n: (vib[n] if declared and self.vibration_scale > 0 else None) for n in self._base_cov}
        self._vib_factor = {n: None if C is None else _psd_factor(C) for n, C in self._vib_cov.items()}
        for n, C in self._cal_cov.items():   # a camera whose calibration is the map's keeps it
            if C is None:
                self._vib_cov[n], self._vib_factor[n] = self._ext_cov[n], self._ext_factor[n]
        self._verdict = None   # the model changed: the consistency is tested again

    def _use_map_covariance(self, ring: CameraRing) -> None:
        """The map's covariance for the cameras whose extrinsics in force are the map's."""
        mm = self.marker_map
        if mm.ring_extrinsics_covariance is None or mm.ring_base_frame != ring.base_frame:
            return
        names = [n for n in mm.ring_covariance_cameras if n in self._T_base_cam
                 and _same_pose(self._T_base_cam[n], mm.ring_extrinsics.get(n))]
        if not names:
            return
        pos = {n: k for k, n in enumerate(mm.ring_covariance_cameras)}
        sel = np.concatenate([6 * pos[n] + np.arange(6) for n in names])
        A = np.zeros((6 * len(names), 6 * len(names)))
        for k, n in enumerate(names):
            A[6 * k:6 * k + 6, 6 * k:6 * k + 6] = geo.se3_adjoint(self._T_base_cam[n])
        full = A @ mm.ring_extrinsics_covariance[np.ix_(sel, sel)] @ A.T
        self._ext_full = 0.5 * (full + full.T)
        self._ext_index = {n: k for k, n in enumerate(names)}
        for k, n in enumerate(names):
            self._ext_cov[n] = self._ext_full[6 * k:6 * k + 6, 6 * k:6 * k + 6].copy()
            self.extrinsics_source[n] = "map"

    def _cross_covariance(self, views: Sequence[CameraView]) -> Optional[np.ndarray]:
        """(6C, 6C) covariance between the views' extrinsic errors, diagonal blocks zero, or None."""
        if self._ext_full is None:
            return None
        names = tuple(v.name for v in views)
        hit = self._cross_cache.get(names)
        if hit is not None:   # the same cameras as a recent frame: the same numbers (read-only)
            return hit[0]
        idx = [self._ext_index.get(v.name) for v in views]
        if sum(i is not None for i in idx) < 2:
            out = None
        else:
            C = len(views)
            out = np.zeros((6 * C, 6 * C))
            for a, ia in enumerate(idx):
                for b, ib in enumerate(idx):
                    if a != b and ia is not None and ib is not None:
                        out[6 * a:6 * a + 6, 6 * b:6 * b + 6] = self._ext_full[6 * ia:6 * ia + 6, 6 * ib:6 * ib + 6]
            out.flags.writeable = False
        if len(self._cross_cache) >= 64:
            self._cross_cache.clear()
        self._cross_cache[names] = (out,)
        return out

    def _problem(self, views: Sequence[CameraView]) -> JointProblem:
        return JointProblem(views, sigma=self.params.pixel_noise, cross_covariance=self._cross_covariance(views))

    # --- input ------------------------------------------------------------------------------

    def _gather(self, ring_frame: RingFrame, rejected: Dict[str, int],
                motion: Optional[MotionModel] = None) -> Dict[str, CameraView]:
        """Per camera, the detections of mapped markers (others counted as ``unknown id``).

        The detections must be sanitized already (:func:`detections.sanitize_observations`:
        finite, convex, unique ids, not ignored): the pipeline does it once, where they enter.
        With ``motion``, a camera whose stamp differs from the ring frame's is moved by the robot's
        displacement in between (:meth:`_moved_extrinsics`).
        """
        mm = self.marker_map
        views: Dict[str, CameraView] = {}
        t_ref = float(ring_frame.stamp)
        for name, cf in ring_frame.cameras.items():
            if not cf.observations:
                continue
            if name not in self._T_cam_base:
                rejected[REJECT_NO_MODEL] = rejected.get(REJECT_NO_MODEL, 0) + len(cf.observations)
                continue
            obs = [o for o in cf.observations if int(o.marker_id) in mm]
            unknown = len(cf.observations) - len(obs)
            if unknown:
                rejected[REJECT_UNKNOWN_ID] = rejected.get(REJECT_UNKNOWN_ID, 0) + unknown
            if not obs:
                continue
            ids = [int(o.marker_id) for o in obs]
            T_cam_base, T_base_cam = self._T_cam_base[name], self._T_base_cam[name]
            ext_cov, ext_factor = ((self._vib_cov[name], self._vib_factor[name]) if self._calibration_cleared
                                   else (self._ext_cov[name], self._ext_factor[name]))
            moved = None if motion is None or cf.stamp == t_ref else motion(t_ref, float(cf.stamp))
            shared = None
            if moved is not None:
                T_cam_base, T_base_cam, ext_cov = self._moved_extrinsics(T_base_cam, ext_cov, moved[0], moved[1])
                ext_factor = None
                if len(moved) > 2 and moved[2] is not None and ext_cov is not None:
                    shared = body_factor_to_perturbation(moved[2])
            map_factor = self._map_factor(ids)
            views[name] = CameraView(name=name, T_cam_base=T_cam_base,
                                     model=cf.model if cf.model is not None else self.ring[name].model, ids=ids,
                                     px=np.concatenate([np.asarray(o.corners, dtype=np.float64) for o in obs]),
                                     X=np.concatenate([mm.corners(i) for i in ids]),
                                     T_base_cam=T_base_cam, extrinsics_cov=ext_cov,
                                     extrinsics_factor=ext_factor, map_factor=map_factor, shared_factor=shared)
        return views

    def _map_factor(self, ids: Sequence[int]) -> Optional[np.ndarray]:
        """(4k, 3, 6) the markers' map-uncertainty factors (:func:`marker_map_factor`, cached by id),
        or None when the model is off or these markers' poses are exact (a surveyed or true map)."""
        if self.params.fusion != "joint" or not self.params.map_uncertainty:
            return None
        key = tuple(ids)
        try:
            return self._view_factor_cache[key]
        except KeyError:
            pass
        out = self._view_factor(ids)
        if out is not None:
            out.flags.writeable = False   # shared by every frame that sees these markers
        if len(self._view_factor_cache) >= 256:
            self._view_factor_cache.clear()
        self._view_factor_cache[key] = out
        return out

    def _view_factor(self, ids: Sequence[int]) -> Optional[np.ndarray]:
        """:meth:`_map_factor` computed (from the per-id cache)."""
        cache = self._map_factor_cache
        rows = []
        for i in ids:
            F = cache.get(i)
            if F is None:
                e = self.marker_map[i]
                F = marker_map_factor(e.T_map_marker, self.marker_map.corners(i), e.position_std, e.rotation_std)
                # An exact marker (zero stds) is cached as False: a frame of exact markers (a
                # surveyed or true map) costs no array work.
                F = cache[i] = F if np.any(F != 0.0) else False
            rows.append(F)
        if not any(F is not False for F in rows):
            return None
        return np.concatenate([np.zeros((4, 3, 6)) if F is False else F for F in rows])

    @staticmethod
    def _moved_extrinsics(T_base_cam: np.ndarray, ext_cov: Optional[np.ndarray], d: np.ndarray,
                          cov_d: np.ndarray) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
        """A free-running camera's extrinsics at the ring frame's stamp (issue 12).

        The camera saw the map at its own stamp ``t_c``, when base_link was at
        ``T_map_base(t_ref) · D`` (``D``: the planar displacement ``d`` from ``t_ref`` to ``t_c``
        in the body frame at ``t_ref``). So for the pose at ``t_ref`` it is a camera mounted at
        ``D · T_base_cam``; nothing else in the estimator changes. The displacement's error
        ``eps`` (3x3 ``cov_d`` over x, y, yaw) is a left perturbation of that mounting in the base
        frame, as an extrinsic error is: ``exp(eps) · D · T_base_cam``; the extrinsics' own
        ``Sigma`` is carried through ``D`` (``Ad_D Sigma Ad_D^T``) and the two add. Returns
        ``(T_cam_base, T_base_cam, extrinsics_cov)``; the covariance is None only when both are
        (negligible: a zero displacement error).
        """
        D = displacement_to_transform(d)
        T_bc = D @ T_base_cam
        cov = None
        if ext_cov is not None:
            A = geo.se3_adjoint(D)
            cov = A @ ext_cov @ A.T
        if cov_d is not None and np.any(np.asarray(cov_d) > 0):
            C = body_covariance_to_perturbation(cov_d)
            cov = C if cov is None else cov + C
        if cov is not None:
            cov = 0.5 * (cov + cov.T)
        return _inv(T_bc), T_bc, cov

    # --- per camera -------------------------------------------------------------------------

    def _camera_estimate(self, view: CameraView, T_ref: Optional[np.ndarray]) -> Tuple[CameraEstimate, List[np.ndarray]]:
        """One camera's PnP estimate; also returns the single-marker alternatives (T_map_base).

        A single marker has two IPPE solutions. When the image tells them apart
        (:meth:`_ippe_ambiguous` is False) the one that reprojects better is taken, whatever
        ``T_ref`` says: a wrong reference (a kidnapped robot's prediction) never overrules a clear
        image. Otherwise the one nearer ``T_ref`` (the prediction, or another camera's estimate)
        is taken and the estimate is marked ``ambiguous``.
        """
        mm = self.marker_map
        T_cam_base = view.T_cam_base
        alternatives: List[np.ndarray] = []
        ambiguity = 0.0
        ambiguous = False
        if len(view.ids) == 1:
            cand = solve_marker_ippe(view.px, mm[view.ids[0]].size, view.model, normalized=view.xy)
            T_map_marker = mm.T_map_marker(view.ids[0])
            options = [T_map_marker @ geo.inverse(T) for T in cand.poses]  # T_map_cam
            bases = [T @ T_cam_base for T in options]
            ambiguous = len(options) > 1 and self._ippe_ambiguous(cand.errors, cand.ambiguity)
            pick = 0
            if ambiguous and T_ref is not None:
                pick = int(np.argmin([_pose_gap(B, T_ref) for B in bases]))
            T_map_cam = options[pick]
            err = cand.errors[pick]
            ambiguity = cand.ambiguity
            alternatives = bases
        else:
            T_init = None if T_ref is None else geo.inverse(T_ref @ geo.inverse(T_cam_base))
            T_cam_map, err = solve_points(view.X, view.px, view.model, T_init=T_init, normalized=view.xy)
            if T_init is not None and err > self.params.max_reprojection_error:
                T_cam_map, err = solve_points(view.X, view.px, view.model, normalized=view.xy)  # restart globally
            T_map_cam = geo.inverse(T_cam_map)
        est = self._make_estimate(view, T_map_cam, float(err), float(ambiguity))
        est.ambiguous = ambiguous
        return est, alternatives

    def _ippe_ambiguous(self, errors: Sequence[float], ratio: float) -> bool:
        """Whether the image cannot tell a marker's two IPPE poses apart: their ratio of RMS errors
        is above ``ambiguity_gate``, or their chi^2 (4 corners, ``pixel_noise``) differ by less
        than ``ambiguity_chi2`` -- two poses that both fit within the noise (0.06 and 0.22 px at
        0.5 px noise) are ambiguous however small their ratio."""
        p = self.params
        d_chi2 = 4.0 * (errors[1] ** 2 - errors[0] ** 2) / p.pixel_noise ** 2
        return ratio > p.ambiguity_gate or d_chi2 < p.ambiguity_chi2

    def _make_estimate(self, view: CameraView, T_map_cam: np.ndarray, err: float, ambiguity: float) -> CameraEstimate:
        # Paper: distance to the markers and the angle between the camera's z axis and the
        # markers' z axes (a marker facing the camera has its z anti-parallel to the camera's).
        centres, normals = self._marker_axes(view.ids)
        dists = np.linalg.norm(centres - T_map_cam[:3, 3], axis=1)
        cosines = np.clip(-(normals @ T_map_cam[:3, 2]), -1.0, 1.0)
        est = CameraEstimate(camera=view.name, marker_ids=list(view.ids), T_map_cam=T_map_cam,
                             T_map_base=T_map_cam @ view.T_cam_base, reprojection_error=err,
                             distance=float(np.mean(dists)), angle=float(np.mean(np.arccos(cosines))),
                             ambiguity=ambiguity)
        est.accuracy = accuracy_weight(est.distance, est.angle, self.params.th_distance, self.params.th_orientation)
        if not err <= self.params.max_reprojection_error:
            est.valid = False
            est.reject_reason = REJECT_REPROJECTION
        return est

    def _per_camera(self, result: LocalizationResult, views: Dict[str, CameraView],
                    prediction: Optional[np.ndarray]) -> Dict[str, List[np.ndarray]]:
        """PnP per camera (paper step 2): multi-marker cameras first, then single markers
        resolved against the prediction, a multi-marker camera, or the least ambiguous one.
        Returns both IPPE solutions (T_map_base) of every single-marker camera."""
        rejected = result.rejected
        order = sorted(views, key=lambda n: -len(views[n].ids))
        T_ref = prediction
        singles: List[str] = []
        alternatives: Dict[str, List[np.ndarray]] = {}
        for name in order:
            view = views[name]
            if len(view.ids) == 1 and T_ref is None:
                T_ref = self._reference_from(result.estimates.values())
            try:
                est, alts = self._camera_estimate(view, T_ref)
            except (MeasurementError, np.linalg.LinAlgError) as exc:
                logger.debug("camera %s: %s", name, exc)
                rejected[REJECT_PNP] = rejected.get(REJECT_PNP, 0) + 1
                continue
            if len(view.ids) == 1:
                singles.append(name)
                alternatives[name] = alts
            result.estimates[name] = est
        if T_ref is None and len(singles) > 1:
            anchor = min(singles, key=lambda n: result.estimates[n].ambiguity)
            T_anchor = result.estimates[anchor].T_map_base
            for name in singles:
                if name != anchor:
                    try:
                        result.estimates[name] = self._camera_estimate(views[name], T_anchor)[0]
                    except MeasurementError:
                        pass
        for est in result.estimates.values():
            if not est.valid:
                rejected[est.reject_reason] = rejected.get(est.reject_reason, 0) + 1
        return alternatives

    def _reference_from(self, estimates) -> Optional[np.ndarray]:
        good = [e for e in estimates if e.valid and len(e.marker_ids) > 1]
        if not good:
            return None
        return min(good, key=lambda e: e.reprojection_error).T_map_base

    # --- the pipeline -----------------------------------------------------------------------

    def process(self, ring_frame: RingFrame, prediction: Optional[np.ndarray] = None,
                motion: Optional[MotionModel] = None) -> LocalizationResult:
        """Localize from one ring frame.

        Args:
            ring_frame: every camera's detections (raw pixels).
            prediction: optional (4, 4) predicted ``T_map_base`` (the filter's), used to resolve
                single-marker ambiguities and to start the joint estimator.
            motion: optional ``motion(t_ref, t_c) -> (d, cov_d)`` or None: the robot's planar
                displacement (x, y, yaw in the body frame at ``t_ref``) from the ring frame's stamp to a
                camera's own stamp and its 3x3 covariance (free-running cameras: each camera is used
                at its own stamp, :meth:`_moved_extrinsics`). None: every camera at the frame's stamp.

        Returns:
            :class:`LocalizationResult` (``T_map_base`` None when nothing usable was seen;
            ``ambiguous`` when the data admit another pose as well).
        """
        p = self.params
        result = LocalizationResult(stamp=float(ring_frame.stamp))
        views = self._gather(ring_frame, result.rejected, motion)
        self.last_views = views
        result.calibration_cleared = self._calibration_cleared and any(self._cal_cov.get(n) is not None for n in views)
        result.marker_ids = sorted({i for v in views.values() for i in v.ids})
        if not views:
            return result
        if p.fusion != "paper" and sum(len(v.ids) for v in views.values()) >= p.min_markers_joint:
            # Every camera with a single marker: each has two IPPE poses and the joint problem may
            # have several minima, so it is solved from all of them (never from the prediction alone).
            prone = all(len(v.ids) == 1 for v in views.values())
            if prediction is not None and not prone:
                # Fast path: start from the prediction; per-camera estimates follow from the result.
                sol = self._try_joint(views, [prediction])
                if sol is not None:
                    self._finish_joint(result, self._exact_if_consistent(sol), per_camera=True)
                    return result
            alternatives = self._per_camera(result, views, prediction)
            starts = [] if prediction is None else [prediction]
            good = sorted((e for e in result.estimates.values() if e.valid), key=lambda e: -e.accuracy)
            starts += [e.T_map_base for e in good[:3]]
            if prone:
                starts += [T for alts in alternatives.values() for T in alts]
                sol = self._resolve_joint(result, views, starts, prediction)
            else:
                sol = self._try_joint(views, starts) if starts else None
            if sol is not None:
                self._finish_joint(result, self._exact_if_consistent(sol), per_camera=False)
                return result
            logger.debug("joint estimator failed; using the paper's fusion")
        else:
            alternatives = self._per_camera(result, views, prediction)
        self._paper(result, views, alternatives)
        return result

    def _paper(self, result: LocalizationResult, views: Dict[str, CameraView],
               alternatives: Dict[str, List[np.ndarray]]) -> None:
        p = self.params
        T, group, w = fuse_paper(list(result.estimates.values()), p.fusion_gap)
        if T is None:
            return
        result.T_map_base = T
        result.method = "paper"
        result.used_cameras = [e.camera for e in group]
        # Ambiguous: the pose rests on single markers whose two IPPE poses the images do not tell
        # apart (several such cameras agree by construction: each took the pose nearest the
        # anchor's; the joint estimator is what weighs them against each other).
        result.ambiguous = all(e.ambiguous for e in group)
        if result.ambiguous:
            result.alternatives = [A for e in group for A in alternatives.get(e.camera, [])
                                   if _pose_gap(A, e.T_map_base) > _SAME_POSE]
        # Covariance: each camera's own Jacobian covariance, combined as independent estimates
        # with the fusion weights: sum w_i^2 C_i.
        cov = np.zeros((6, 6))
        n_points, sq = 0, 0.0
        for e, wi in zip(group, w):
            prob = JointProblem([views[e.camera]])
            r, J = prob.residuals(geo.inverse(e.T_map_base))
            H = np.einsum("nia,nib->ab", J, J)
            sigma = max(p.pixel_noise, e.reprojection_error / np.sqrt(2.0))
            try:
                e.covariance = covariance_from_information(H, sigma, e.T_map_base)
            except MeasurementError:
                e.covariance = np.eye(6)  # a degenerate single view: no information
            cov += wi ** 2 * e.covariance
            rf = geo.inverse(T)
            r_f, _ = JointProblem([views[e.camera]]).residuals(rf, jacobian=False)
            n_points += prob.n
            sq += float(np.sum(r_f[np.isfinite(r_f)] ** 2))
        result.covariance = cov
        result.n_points = n_points
        result.residual_rms = float(np.sqrt(sq / max(n_points, 1)))

    def _resolve_joint(self, result: LocalizationResult, views: Dict[str, CameraView], starts: Sequence[np.ndarray],
                       prediction: Optional[np.ndarray]) -> Optional[_JointSolution]:
        """The joint problem solved from several distinct starts (both IPPE poses of every
        single-marker camera, the per-camera estimates, the prediction), scored by its cost.

        The solution with the fewest dropped markers and the lowest chi^2 wins; another distinct
        solution within ``ambiguity_chi2`` of it makes the result ``ambiguous``, and then the
        one nearer the prediction (when there is one) is taken.
        """
        p = self.params
        problem = self._problem(list(views.values()))
        costs = np.array([problem.cost(geo.inverse(T), p.robust_scale) for T in starts])
        picked: List[np.ndarray] = []
        for k in np.argsort(costs):
            if not np.isfinite(costs[k]) or len(picked) >= _MAX_JOINT_STARTS:
                break
            if all(_pose_gap(starts[k], T) > _SAME_POSE for T in picked):
                picked.append(starts[k])
        sols: List[_JointSolution] = []
        for T0 in picked:
            sol = self._try_joint(views, [T0], problem)
            if sol is not None and all(_pose_gap(geo.inverse(sol.T_base_map), geo.inverse(s.T_base_map)) > _SAME_POSE
                                       for s in sols):
                sols.append(sol)
        if not sols:
            return None
        chi2 = {id(s): s.chi2 for s in sols}
        sols.sort(key=lambda s: (s.outliers, chi2[id(s)]))
        best = sols[0]
        rivals = [s for s in sols[1:] if s.outliers == best.outliers and chi2[id(s)] - chi2[id(best)] < p.ambiguity_chi2]
        # One marker seen by several cameras: their viewpoints resolve its two poses only when the
        # joint problem found the other one too and it lost by ambiguity_chi2 or more; a lone
        # minimum of a far marker seen along nearly one direction proves nothing (every start
        # ends there, decimetres off).
        beaten = [s for s in sols[1:] if s.outliers == best.outliers and
                  chi2[id(s)] - chi2[id(best)] >= p.ambiguity_chi2]
        if rivals or (len(result.marker_ids) < 2 and not beaten):
            result.ambiguous = True
            if prediction is not None:
                best = min([best] + rivals, key=lambda s: _pose_gap(geo.inverse(s.T_base_map), prediction))
            result.alternatives = [geo.inverse(s.T_base_map) for s in [sols[0]] + rivals if s is not best]
        return best

    def _try_joint(self, views: Dict[str, CameraView], starts: Sequence[np.ndarray],
                   problem: Optional[JointProblem] = None) -> Optional[_JointSolution]:
        """Solve from the best of ``starts`` (T_map_base); drop misfit markers; None on failure."""
        p = self.params
        if problem is None:
            problem = self._problem(list(views.values()))
        if len(starts) == 1:
            T0 = starts[0]  # the solver evaluates it anyway; a bad start fails the checks below
        else:
            costs = [problem.cost(geo.inverse(T), p.robust_scale) for T in starts]
            if not np.isfinite(min(costs)):
                return None
            T0 = starts[int(np.argmin(costs))]
        try:
            T_bm, fit, iters = self._solver(problem).solve(geo.inverse(T0), p.robust_scale, p.max_iterations)
            # Drop whole markers that do not fit (a moved or mis-mapped marker) and solve again.
            r = fit.r
            e2 = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
            e2_sum = float(e2.sum())
            finite = math.isfinite(e2_sum)   # finite only when every residual is
            if not finite:
                e2 = np.sum(np.where(np.isfinite(r), r, 1e6) ** 2, axis=1)
            # (the per-marker mean of 4 as sum * 0.25: the same numbers without mean's set-up)
            bad = np.sqrt(e2.reshape(-1, 4).sum(axis=1) * 0.25) > p.joint_outlier_threshold
            outliers = int(bad.sum())
            if outliers:
                if outliers * 2 > bad.size or bad.size - outliers < p.min_markers_joint:
                    return None  # most markers disagree: a wrong start, not outliers
                kept, k = [], 0
                for v in problem.views:
                    m = len(v.ids)
                    keep = [j for j in range(m) if not bad[k + j]]
                    k += m
                    if keep:
                        kept.append(v if len(keep) == m else v.subset(keep))
                problem = self._problem(kept)
                T_bm, fit, it2 = self._solver(problem).solve(T_bm, p.robust_scale, p.max_iterations)
                iters += it2
        except MeasurementError as exc:
            logger.debug("joint estimator: %s", exc)
            return None
        if outliers:
            r = fit.r
            e2 = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
            e2_sum = float(e2.sum())
            finite = math.isfinite(e2_sum)
        if not finite:   # a residual not finite (or, as before, an RMS that would be infinite)
            return None
        rms = math.sqrt(e2_sum / e2.size)   # np.sqrt(e2.mean()): the same sum, divided
        if rms > p.joint_outlier_threshold:
            return None
        sigma = float("nan")
        try:
            if p.estimate_pixel_noise and problem.extrinsics_factor is not None:
                T_bm, fit, iters, rms, cov, cov_map, sigma, gain = self._at_measured_noise(problem, T_bm, fit, iters,
                                                                                           rms)
            else:
                # Variance factor: the whitened residuals' own when they say the noise is larger.
                factor = max(1.0, fit.chi2 / max(2 * problem.n - 6, 1))
                cov = problem.covariance(fit) * factor
                gain = problem.shared_gain(fit)
                gain = None if gain is None else gain * np.sqrt(factor)
                cov_map = problem.map_covariance(fit, T_bm)   # the map's error, carried to the pose
            if cov_map is not None:
                cov = cov + cov_map
            if self._calibration_cleared:
                # The estimate does not weigh the calibration's error; the covariance still carries it.
                H_cam = fit.H_cam if fit.H_cam is not None else \
                    camera_blocks(problem, fit)[0] / (problem.sigma ** 2 * factor)
                cov = cov + self._calibration_covariance(problem.views, H_cam)
        except (np.linalg.LinAlgError, MeasurementError):
            return None
        if not math.isfinite(rms) or rms > p.joint_outlier_threshold:
            return None
        return _JointSolution(problem, T_bm, fit, iters, rms, cov, outliers, sigma, gain)

    def _calibration_covariance(self, views: Sequence[CameraView], H_cam: np.ndarray) -> np.ndarray:
        """(6, 6) what the ring file's calibration error (its declared ``extrinsics_std``) does to a
        pose whose estimate does not weigh it (the window cleared it): the pose responds to camera
        c's error ``eta_c`` by ``K_c = H^-1 H_c`` (``H_cam``: the cameras' information in the model
        solved, ``H`` their sum), so it adds ``sum_c K_c C_c K_c^T`` (the declared errors are
        independent). The window cannot see the cameras' common error (a turn of the whole ring),
        nor a calibration error too small for it: both stay in the covariance."""
        K = np.linalg.solve(H_cam.sum(axis=0)[None], H_cam)   # (C, 6, 6)
        out = np.zeros((6, 6))
        for k, v in enumerate(views):
            C = self._cal_cov.get(v.name)
            if C is not None:
                out += K[k] @ C @ K[k].T
        return 0.5 * (out + out.T)

    def _solver(self, problem: JointProblem) -> JointProblem:
        """``problem`` at the pixel noise the solver weighs the pixels with: with
        ``estimate_pixel_noise`` and a calibration model, the noise measured in the last frame
        (:attr:`pixel_noise_guess`), else ``pixel_noise``."""
        if self.params.estimate_pixel_noise and problem.extrinsics_factor is not None:
            return problem.with_sigma(self.pixel_noise_guess)
        return problem

    def _at_measured_noise(self, problem: JointProblem, T_bm: np.ndarray, fit: JointFit, iters: int, rms: float):
        """The joint solution at the pixel noise its residuals say (``estimate_pixel_noise``).

        The pixel noise weighs the pixels against the extrinsics' (and the vibration's)
        uncertainty; the residuals tell the noise the images really have
        (:meth:`JointProblem.pixel_noise_estimate`, at least ``min_pixel_noise``). ``fit`` (at
        ``T_bm``) was solved at :attr:`pixel_noise_guess`: the noise measured in the last frame
        (``pixel_noise`` before the first). When this frame's noise differs from it by more than
        25 % the cameras weigh differently, so the pose is solved again with it (from the
        solution: one or two iterations); the covariance is that solution's, with that noise (its
        inverse information, the cameras' common extrinsic error and the map's error carried to
        the pose), so estimate and covariance agree. The returned fit is at the measured noise (its
        blocks, residuals and weights are what the later steps read); the ambiguity tests compare
        candidate poses at ``pixel_noise`` (:attr:`_JointSolution.chi2` refits it there).

        Within 25 % the solution at the frame's own noise is one Gauss-Newton step away: that step
        is taken from the per-camera blocks already computed (:meth:`JointProblem.refit`, no new
        residuals), the residuals following it to first order. Starting from the last frame's
        noise rather than from ``pixel_noise`` changes which frames are solved twice, not the
        result: with the detector's 0.1 px against the configured 0.5 px every frame was solved
        twice.

        Returns (T_base_map, fit, iterations, rms, covariance, map covariance or None, the
        measured pixel noise, :meth:`JointProblem.shared_gain` or None)."""
        p = self.params
        solved_at = self.pixel_noise_guess
        sigma = problem.pixel_noise_estimate(fit, p.min_pixel_noise, 100.0 * p.pixel_noise, start=solved_at)
        at = problem.with_sigma(sigma)
        if abs(np.log(sigma / solved_at)) > np.log(1.25):
            T_bm, fit_s, it3 = at.solve(T_bm, p.robust_scale, p.max_iterations)
            iters += it3
            r = fit_s.r
            rms = math.sqrt(np.mean(np.sum(r * r, axis=1))) if np.isfinite(r).all() else float("inf")
        else:
            fit_s = at.refit(fit)   # the same residuals and Huber weights (the scale is in px)
            try:
                delta = -_solve_spd(fit_s.H, fit_s.g)
            except np.linalg.LinAlgError:
                raise MeasurementError("joint estimator: singular normal equations (degenerate geometry)") from None
            # The step keeps the blocks G_c (and so H, H_cam: what the covariances below read); only
            # the gradients follow it, and problem.refit below takes them from b_cam.
            T_bm, fit_s = at.linear_step(T_bm, fit_s, delta)
        return (T_bm, fit_s, iters, rms, at.covariance(fit_s), at.map_covariance(fit_s, T_bm),
                sigma, at.shared_gain(fit_s))

    def _exact_if_consistent(self, sol: _JointSolution) -> _JointSolution:
        """``sol`` (calibration-aware), or the exact-extrinsics solution of the same views when the
        frame's cameras agree with each other through the extrinsics (``exact_when_consistent``).

        The test (:func:`extrinsics_consistency`): at the exact-extrinsics optimum, letting each
        camera have its own pose lowers the squared residuals by ``D`` (``6(C-1)`` degrees of
        freedom); what is left, ``S`` (``2N - 6C``), is the pixel noise within the cameras, which
        no extrinsic error touches (a camera's extrinsic error moves its points as a robot
        motion does). With exact extrinsics ``F = (D / 6(C-1)) / (S / (2N - 6C))`` is F-distributed;
        an extrinsic error the data can see inflates it. Below the ``1 - consistency_alpha``
        quantile the data do not contradict the calibration, and the extrinsics are taken as
        exact (the maximum-likelihood pose under pixel noise; what the calibration-aware model
        gives up there is efficiency: on TagSLAM's rigs, whose extrinsics are its optimum on the
        same data, it moved the pose by 2-4 mm). The covariance stays the calibration-aware one
        (it carries the extrinsics' and the map's uncertainty; a larger one is the safe side),
        except for the views' common error (free-running cameras moved with one velocity): the
        test cannot see it (it moves all cameras alike but for their ``dt``), and the
        exact-extrinsics pose responds to it with its own gain ``K_x = G^-1 sum_c G_c F_c``
        (``G_c = J_c^T D_c J_c``), so its part ``K K^T`` of the covariance is replaced by
        ``K_x K_x^T`` (what is left, ``P - K K^T``, is the covariance of the pixel noise and the
        independent errors)."""
        p = self.params
        problem = sol.problem
        if self._calibration_cleared and problem.extrinsics_factor is None and len(problem.views) >= 2:
            # Cleared, and the ring declares no vibration: the frame is exact already; the window goes on.
            self._window_update(problem, sol.fit)
        if (not p.exact_when_consistent or p.fusion != "joint" or problem.extrinsics_factor is None
                or len(problem.views) < 2):
            return sol
        # The same cameras on the same markers as the last frame tested, which was far beyond the
        # clear verdict, and the robot within _VERDICT_MOVE of where it was then (parked or
        # creeping: the same view of the same markers): the same verdict (inconsistent) without
        # testing, up to _VERDICT_REUSE frames in a row (issue 16: ~0.25 ms a frame; F then moves
        # with the pixel noise only, 80-300 times the quantile on the lab's frames, so a tenth of it
        # cannot fall below _F_CLEAR). A moving rig is tested every frame (on test_8 F spreads from
        # 0.9 to 14.5 times the quantile, p10-p90, as the rig moves).
        views_key = tuple((v.name, tuple(v.ids)) for v in problem.views)
        last = self._verdict
        R_bm = sol.T_base_map[:3, :3]
        position = -(R_bm.T @ sol.T_base_map[:3, 3])   # the robot's, in the map
        if last is not None and last[0] == views_key and last[1] < _VERDICT_REUSE and \
                float(np.abs(position - last[2]).max()) <= _VERDICT_MOVE and \
                float(np.abs(sol.T_base_map[:3, :3] - last[3]).max()) <= _VERDICT_MOVE:
            self._verdict = (views_key, last[1] + 1, last[2], last[3])
            return sol
        self._verdict = None
        exact = problem.exact()
        fit1 = test = None
        recorded = False   # this frame in the window (persistence_window)
        try:
            start = sol.T_base_map
            if sol.fit.G_cam is not None and np.isfinite(sol.fit.r).all():
                # The verdict first, from one Gauss-Newton step on the blocks the calibration-aware
                # fit holds (JointProblem.exact_step, no residuals evaluated): its F is within a few
                # per cent of the solved one's (2 % on the lab, where F is 100 times the quantile).
                # Clearly inconsistent (> _F_CLEAR times the quantile): no second solve. Otherwise
                # the exact pose is solved from that step, and judged there as before.
                T1, fit1, norm = exact.exact_step(sol.T_base_map, sol.fit, p.robust_scale)
                test = extrinsics_consistency(exact, fit1)
                recorded = self._window_update(exact, fit1)
                if test is not None and test[0] > _F_CLEAR * _f_quantile(1.0 - p.consistency_alpha, test[1], test[2]):
                    if test[0] > _F_REUSE * _f_quantile(1.0 - p.consistency_alpha, test[1], test[2]):
                        self._verdict = (views_key, 0, position, R_bm.copy())
                    return sol
                start = T1
            if start is not sol.T_base_map and norm <= _EXACT_STEP:
                # A small step is the exact optimum already (on the lab's consistent frames, steps of
                # 0.5-4.4 mm / mrad: 5e-8 m from the solved pose at most): no second solve.
                T_bm, fit, iters = T1, fit1, 1
            else:
                T_bm, fit, iters = exact.solve(start, p.robust_scale, p.max_iterations)
                test = None
        except MeasurementError:
            return sol
        r = fit.r
        if not np.isfinite(r).all():
            return sol
        if fit is not fit1:
            test = extrinsics_consistency(exact, fit)
        if not recorded:
            self._window_update(exact, fit)
        if test is None or test[0] > _f_quantile(1.0 - p.consistency_alpha, test[1], test[2]):
            return sol
        rms = math.sqrt(np.mean(np.sum(r * r, axis=1)))
        if not rms <= p.joint_outlier_threshold:
            return sol
        cov, gain = sol.covariance, None
        if sol.shared_gain is not None:
            G = fit.G_cam   # the one-step exact fit carries the per-camera blocks; a solved one does not
            if G is None:
                G = np.add.reduceat(np.einsum("nia,nib->nab", fit.J * fit.w[:, None, None], fit.J),
                                    exact.offsets[:-1], axis=0)
            try:
                gain = _shared_gain(fit.H, G / exact.sigma ** 2, problem.shared_factor)
            except (np.linalg.LinAlgError, MeasurementError):
                return sol
            cov = cov - sol.shared_gain @ sol.shared_gain.T + gain @ gain.T
            cov = 0.5 * (cov + cov.T)
        return _JointSolution(exact, T_bm, fit, sol.iterations + iters, rms, cov, sol.outliers, shared_gain=gain)

    def _window_update(self, exact: JointProblem, fit: JointFit) -> bool:
        """This frame (``fit``: at the exact-extrinsics optimum of ``exact``, or the step to it) into
        the window (:class:`CalibrationPersistence`), and the window's verdict for the next frames
        (:attr:`calibration_cleared`): the ring's calibration is borne out when over the window the
        cameras' disagreement does not follow them (``rho <= persistence_max`` over at least
        ``persistence_min_pairs`` pairs of frames). A frame with a camera the ring declares
        non-rigid (``wiggle``: it moves against the rig in every frame) is not recorded, and the
        calibration stays. Returns whether the frame was recorded."""
        p = self.params
        if p.persistence_window <= 0 or any(v.name in self._wiggling for v in exact.views):
            self._calibration_cleared = False
            return False
        G, b = camera_blocks(exact, fit)
        self.persistence.add([v.name for v in exact.views], [v.ids for v in exact.views], G, b)
        rho, pairs = self.last_persistence = self.persistence.correlation()
        self._calibration_cleared = bool(pairs >= max(p.persistence_min_pairs, 1) and rho <= p.persistence_max)
        if p.estimate_vibration and (p.extrinsic_jitter_deg > 0 or p.extrinsic_jitter_m > 0):
            self._vibration_update(exact, fit, G, b)
        return True

    def _vibration_update(self, exact: JointProblem, fit: JointFit, G: np.ndarray, b: np.ndarray) -> None:
        """This frame into the vibration estimate (:class:`VibrationEstimate`), and the scale of the
        declared vibration the next frames are solved with: the estimate's upper one-sigma bound
        ``kappa^2 + se``, within [0, 1] (the declared jitter is an upper bound), once the window
        holds ``vibration_min_pairs`` pairs and the estimate is not more than two standard errors
        below zero; else 1 (the declared). The covariances are rebuilt
        only when the jitter (``kappa``) moves by more than 2 % of the declared."""
        p = self.params

        def noise() -> float:   # px^2: the pixel noise within the cameras (extrinsics_consistency's)
            d2 = 2 * exact.n - 6 * len(exact.views)
            if d2 < 1:
                return float("nan")
            return (float(np.sum(fit.weighted_squares())) - _sum_pinv_quadratic(G, b)) / d2

        self.vibration.add([v.name for v in exact.views], [v.ids for v in exact.views], G, b, noise,
                           [self._vib_declared[v.name] for v in exact.views])
        k2, se, pairs = self.last_vibration = self.vibration.estimate()
        # More than two standard errors below zero: the pixel noise term predicts more spread than
        # there is (it holds errors the pairs remove), so the estimate is no evidence: declared.
        usable = pairs >= max(p.vibration_min_pairs, 1) and k2 + 2.0 * se >= 0.0
        scale = float(np.clip(k2 + se, 0.0, 1.0)) if usable else 1.0
        if abs(np.sqrt(scale) - np.sqrt(self.vibration_scale)) > 0.02:
            self._apply_vibration(scale)

    def _finish_joint(self, result: LocalizationResult, sol: _JointSolution, per_camera: bool) -> None:
        problem = sol.problem
        if math.isfinite(sol.pixel_noise):
            self.pixel_noise_guess = sol.pixel_noise   # the next frame is solved at it
        T_map_base = _inv(sol.T_base_map)
        result.covariance = map_frame_covariance(sol.covariance, T_map_base)
        result.T_map_base = T_map_base
        result.method = "joint"
        result.used_cameras = [v.name for v in problem.views]
        result.n_points = problem.n
        result.residual_rms = sol.rms
        result.iterations = sol.iterations
        result.extrinsics_consistent = sol.problem.extrinsics_factor is None and self.params.fusion == "joint" \
            and self._ext_factor_any
        if sol.outliers:
            result.rejected[REJECT_OUTLIER] = result.rejected.get(REJECT_OUTLIER, 0) + sol.outliers
        if per_camera:
            # Computed when first read (the node's ~camera_estimates with a subscriber, the
            # benchmarks): most frames nobody reads them (issue 16: ~0.2 ms a frame).
            result.estimates = LazyMapping(lambda out: self._per_camera_from_joint(out, sol, self.params))

    def forget_marker(self, marker_id: int) -> None:
        """Drop what is cached of a marker (its pose in the map changed: re-mapped)."""
        self._axes_cache.pop(int(marker_id), None)
        self._map_factor_cache.pop(int(marker_id), None)
        self._view_factor_cache.clear()

    def _marker_axes(self, ids: Sequence[int]) -> Tuple[np.ndarray, np.ndarray]:
        """(k, 3) centres and (k, 3) z axes of mapped markers, in the map frame (cached by id)."""
        cache = self._axes_cache
        rows = []
        for i in ids:
            row = cache.get(i)
            if row is None:
                T = self.marker_map.T_map_marker(i)
                row = cache[i] = np.concatenate([T[:3, 3], T[:3, 2]])
            rows.append(row)
        arr = np.array(rows)
        return arr[:, :3], arr[:, 3:]

    def _per_camera_from_joint(self, out: Dict[str, CameraEstimate], sol: _JointSolution,
                               p: LocalizationParams) -> None:
        """Each camera's own estimate as one Gauss-Newton step on its rows from the joint pose
        (first order; its rows are already computed, so this is a batched 6x6 solve), into ``out``.
        The reprojection error is the linearised one. Vectorised over cameras."""
        prob = sol.problem
        starts = prob.offsets[:-1]
        if sol.fit.G_cam is not None:  # the joint fit's own per-camera blocks (Huber-weighted)
            Hc, gc = sol.fit.G_cam + _EYE6_TINY, sol.fit.b_cam
        else:
            Hc = np.add.reduceat(np.einsum("nia,nib->nab", sol.J, sol.J), starts, axis=0) + _EYE6_TINY
            gc = np.add.reduceat(np.einsum("nia,ni->na", sol.J, sol.r), starts, axis=0)
        try:
            deltas = -_solve_spd_batch(Hc, gc[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            return
        r_lin = sol.r + np.matmul(sol.J, deltas[prob.cam_index][:, :, None])[:, :, 0]
        counts = prob.counts
        errs = np.sqrt(np.add.reduceat(np.einsum("ni,ni->n", r_lin, r_lin), starts) / counts)
        T_map_cams = _per_camera_poses(sol.T_base_map, deltas, prob.T_base_cams)
        # Distance and angle per marker (4 rows each, cameras' markers in order), averaged per camera
        # (paper's Ac inputs).
        n_per = counts // 4
        cam_of = prob.cam_index[::4]
        axes = self._marker_axes_of(prob)
        Tc = T_map_cams[cam_of]
        dists = np.linalg.norm(axes[:, :3] - Tc[:, :3, 3], axis=1)
        angles = np.arccos(np.clip(-np.einsum("ki,ki->k", axes[:, 3:], Tc[:, :3, 2]), -1.0, 1.0))
        mstarts = starts // 4
        mean_d = np.add.reduceat(dists, mstarts) / n_per
        mean_a = np.add.reduceat(angles, mstarts) / n_per
        ac_d = np.maximum((p.th_distance - mean_d) / p.th_distance, 0.0)
        ac_or = np.maximum((p.th_orientation - mean_a) / p.th_orientation, 0.0)
        acc = 0.5 * (ac_d + ac_or)
        big = (np.einsum("ca,ca->c", deltas, deltas) > 0.25).tolist()
        T_map_bases = T_map_cams @ prob.T_cam_bases
        errs_l, d_l, a_l, acc_l = errs.tolist(), mean_d.tolist(), mean_a.tolist(), acc.tolist()
        max_err = p.max_reprojection_error
        for k, view in enumerate(prob.views):
            if big[k]:
                continue  # not a small correction (above 0.5): this camera alone is not well determined
            est = CameraEstimate(camera=view.name, marker_ids=list(view.ids), T_map_cam=T_map_cams[k],
                                 T_map_base=T_map_bases[k], reprojection_error=errs_l[k],
                                 distance=d_l[k], angle=a_l[k], accuracy=acc_l[k])
            if not errs_l[k] <= max_err:
                est.valid = False
                est.reject_reason = REJECT_REPROJECTION
            out[view.name] = est

    def _marker_axes_of(self, prob: JointProblem) -> np.ndarray:
        """(k, 6) centres and z axes of ``prob``'s markers (in its order), in the map frame."""
        cache = self._axes_cache
        rows = []
        for i in prob.marker_ids.tolist():
            row = cache.get(i)
            if row is None:
                T = self.marker_map.T_map_marker(i)
                row = cache[i] = np.concatenate([T[:3, 3], T[:3, 2]])
            rows.append(row)
        return np.array(rows)


#: The per-camera steps' damping (:meth:`RingLocalizer._per_camera_from_joint`).
_EYE6_TINY = 1e-9 * np.eye(6)
#: The consistency test's F from the linearised exact-extrinsics step above this many times its
#: quantile is taken as the verdict (inconsistent) without solving the exact problem.
_F_CLEAR = 2.0
#: A frame whose F was above this many times its quantile lends its verdict (inconsistent) to the
#: next frames with the same cameras on the same markers, this many in a row, untested
#: (:meth:`RingLocalizer._exact_if_consistent`).
_F_REUSE = 20.0
_VERDICT_REUSE = 4
#: ... while the robot is within this of where the verdict was tested (per coordinate of its
#: position in the map, m, and per entry of ``T_base_map``'s rotation matrix, ~rad).
_VERDICT_MOVE = 0.005
#: m + rad: an exact-extrinsics step (JointProblem.exact_step) up to this is taken as its optimum;
#: above it the pose is solved from there (its second-order error grows as step^2 x the distance
#: to the markers: 2.6 mm at the 0.02 steps of an inconsistent frame, 5e-8 m below 4.4e-3).
_EXACT_STEP = 5e-3
_SAME_POSE = 0.02  # two candidate poses closer than this (m + rad, _pose_gap) are one
# At most this many distinct starts are solved when every camera sees a single marker (two IPPE
# poses each, the per-camera estimates, the prediction: the lowest-cost few hold the minima).
_MAX_JOINT_STARTS = 4


def _same_pose(T_a: np.ndarray, T_b: Optional[np.ndarray], tol: float = 1e-6) -> bool:
    """True when two extrinsics are the same numbers up to a file/tf round trip."""
    if T_b is None:
        return False
    return bool(np.max(np.abs(np.asarray(T_a)[:3] - np.asarray(T_b)[:3])) <= tol)


def _pose_gap(T_a: np.ndarray, T_b: np.ndarray, metres_per_rad: float = 1.0) -> float:
    """Distance between two robot poses for choosing among candidates (m + m/rad * rad)."""
    d, a = geo.pose_distance(T_a, T_b)
    return d + metres_per_rad * a
