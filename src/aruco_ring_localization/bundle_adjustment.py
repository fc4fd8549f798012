"""Bundle adjustment of a marker map: marker poses, robot (station) poses and optionally the ring.

Unknowns (all in one frame W, the robot's base frame at the reference station):

* ``T_W_marker`` for every marker but the fixed one (the gauge: the reference marker),
* ``T_W_base`` for every station (a robot placement; many frames may share one),
* optionally ``T_base_cam`` of every camera, with a Gaussian prior around the calibration.

Optional priors (:class:`MarkerPriors`, the anchors of a surveyed frame: :mod:`anchors`): a
surveyed position of a marker's centre (``(t - p) / std`` per axis), a surveyed orientation
(``log(R R_s^T) / std``) and a level station (the x, y components of its z axis over a sigma: the
robot's floor is the frame's plane). They can replace the fixed station as the gauge: 3 surveyed
points not on a line, or one surveyed pose, fix all 6 degrees of freedom; 2 points fix 5 and one
level station the remaining tilt. A relative-pose prior ties two markers (a tag loose on its board
to the board's frame, :mod:`boards`): the markers' block of the information is then no longer
block diagonal, and the steps and covariances factorise it as a sparse matrix.

Measurements: every detected corner of every observation. A corner ``X`` (marker frame) is seen by
camera ``c`` of station ``s`` at ``p_c = T_base_cam^-1 · T_W_base^-1 · T_W_marker · X``, and the
residual is ``A · (p_c.xy / p_c.z - xy_obs) / pixel_noise`` where ``xy_obs`` are the observed
corners undistorted to normalised coordinates (``CameraModel.normalize``) and ``A`` the 2x2
Jacobian of the raw pixels with respect to them at the observed corner (``obs_lens``; by default
``diag(f)``, the ideal pinhole camera): the raw pixel reprojection error to first order, in units
of the expected corner noise. Undistorting once keeps the lens model out of the solver, and the
local lens scale keeps a fisheye's border corners weighted as what they are.

Optional relative-pose factors (:class:`RelativePoseFactors`, the robot's odometry between two
stations, :mod:`mapping_odometry`): the measured motion ``Z = (R_z, t_z)`` of the base frame from
station ``i`` to station ``j`` (expressed in ``i``) against the estimate ``T_i^-1 T_j``, residual
``(log(R_z^T R_i^T R_j) / sigma_rot, (R_i^T (t_j - t_i) - t_z) / sigma_trans)`` per axis, each
factor with its own sigmas (the odometry's noise model: grows with the distance and the angle
travelled). Odometry glitches (a VIO reset, a jump) are down-weighted by a Huber loss on the
factor's whitened norm (``robust_scale`` sigmas): one weight for its 6 rows.

Each pose is a perturbation of its initial value, ``R = exp(w) R0``, ``t = t0 + dt`` (w in the
parent frame), so the parameters stay near zero. The Jacobian is analytic (left Jacobian of
SO(3) included) and sparse; the solver is Levenberg-Marquardt on the sparse normal equations
(``solver: lm``, :func:`_solve_lm`): ``H = J^T W J`` assembled from each observation's 8 x 18
block (:meth:`_Model.normal_equations`), the markers eliminated block by block (Schur complement)
and the reduced system over stations and cameras solved directly (:meth:`_Model.solve_damped`) --
or, when the stations' unknowns outnumber the markers' (a handheld walk, a calibration recording of
1,500 frames), the stations eliminated instead (block by block, banded with odometry) and the small
dense system over markers and cameras solved (:meth:`_Model._station_elimination`),
the robust loss by reweighting; or :func:`scipy.optimize.least_squares` (``solver: trf``:
``lsmr`` on the sparse Jacobian, ``x_scale='jac'``, a robust loss).

Uncertainty: the Gauss–Newton information ``H = JᵀJ`` at the solution (with the robust loss's
weights), scaled by the residual variance factor. Markers only touch stations and cameras, so
``H = [[A, B], [Bᵀ, C]]`` with ``A`` block diagonal (6x6 per marker); the marginal covariance of
marker ``i`` is exactly ``A_i⁻¹ + A_i⁻¹ B_i S⁻¹ B_iᵀ A_i⁻¹`` with the reduced system
``S = C - Bᵀ A⁻¹ B`` (stations and cameras only, small). This avoids inverting ``H``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from . import geometry as geo
from .config import in_radians, param, require_positive
from .errors import ConfigError, GeometryError
from .markers import marker_corners

logger = logging.getLogger(__name__)


@dataclass
class MarkerPriors:
    """Priors of the adjustment other than the corners: surveyed markers and level stations.

    Attributes:
        position_marker: (K,) indices of markers with a surveyed centre.
        position: (K, 3) those centres in the problem's frame W, m.
        position_std: (K, 3) their 1-sigma per axis of W, m.
        rotation_marker: (L,) indices of markers with a surveyed orientation.
        rotation: (L, 3, 3) those orientations in W.
        rotation_std: (L,) their 1-sigma, rad.
        level_station: (J,) indices of stations whose z axis is held along W's z (the robot stands on
            the frame's plane), with 1-sigma ``level_sigma`` (rad) on each tilt component.
        distance_marker: (D, 2) indices of the two markers of each measured distance (survey
            measurements, :class:`anchors.DistanceMeasurement`), ``distance_point`` (D, 2, 3) the
            two points in those markers' frames, ``distance`` (D,) the measured length and
            ``distance_std`` (D,) its 1-sigma, m: ``r = (|p_a - p_b| - distance) / std``.
        plane_marker: (P,) index of the marker of each point on a measured plane, ``plane_point``
            (P, 3) the point in the marker's frame, ``plane_normal`` (P, 3) the plane's unit normal
            in W, ``plane_offset`` (P,) and ``plane_std`` (P,) m: ``r = (n . p - offset) / std``.
        relative_marker: (Q, 2) markers (a, b) whose relative pose ``T_a^-1 T_b`` is known up to
            a play (a tag loose on its board: a = the board's frame, an unknown with no
            observations, b = the tag), ``relative_pose`` (Q, 4, 4) that pose (the layout),
            ``relative_position_std`` (Q,) m and ``relative_rotation_std`` (Q,) rad its 1-sigma:
            ``r = (log(R_ab^T R_a^T R_b) / rot_std, (R_a^T (t_b - t_a) - t_ab) / pos_std)``, 6 rows.
    """

    position_marker: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    position: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    position_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rotation_marker: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    rotation: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    rotation_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    level_station: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    level_sigma: float = 1e-6
    distance_marker: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=int))
    distance_point: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    distance_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    plane_marker: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    plane_point: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_offset: np.ndarray = field(default_factory=lambda: np.zeros(0))
    plane_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    relative_marker: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=int))
    relative_pose: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    relative_position_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    relative_rotation_std: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.position_marker = np.asarray(self.position_marker, dtype=int).reshape(-1)
        self.position = np.asarray(self.position, dtype=float).reshape(-1, 3)
        self.position_std = np.asarray(self.position_std, dtype=float).reshape(-1, 3)
        self.rotation_marker = np.asarray(self.rotation_marker, dtype=int).reshape(-1)
        self.rotation = np.asarray(self.rotation, dtype=float).reshape(-1, 3, 3)
        self.rotation_std = np.asarray(self.rotation_std, dtype=float).reshape(-1)
        self.level_station = np.asarray(self.level_station, dtype=int).reshape(-1)
        K, L = len(self.position_marker), len(self.rotation_marker)
        if self.position.shape[0] != K or self.position_std.shape[0] != K or self.rotation.shape[0] != L \
                or self.rotation_std.shape[0] != L:
            raise GeometryError("MarkerPriors: the arrays of one kind of prior must have the same length")
        if np.any(self.position_std <= 0) or np.any(self.rotation_std <= 0) or not self.level_sigma > 0:
            raise GeometryError("MarkerPriors: every std must be positive")
        self.distance_marker = np.asarray(self.distance_marker, dtype=int).reshape(-1, 2)
        self.distance_point = np.asarray(self.distance_point, dtype=float).reshape(-1, 2, 3)
        self.distance = np.asarray(self.distance, dtype=float).reshape(-1)
        self.distance_std = np.asarray(self.distance_std, dtype=float).reshape(-1)
        self.plane_marker = np.asarray(self.plane_marker, dtype=int).reshape(-1)
        self.plane_point = np.asarray(self.plane_point, dtype=float).reshape(-1, 3)
        self.plane_normal = np.asarray(self.plane_normal, dtype=float).reshape(-1, 3)
        self.plane_offset = np.asarray(self.plane_offset, dtype=float).reshape(-1)
        self.plane_std = np.asarray(self.plane_std, dtype=float).reshape(-1)
        D, P = len(self.distance_marker), len(self.plane_marker)
        if len(self.distance_point) != D or len(self.distance) != D or len(self.distance_std) != D \
                or len(self.plane_point) != P or len(self.plane_normal) != P or len(self.plane_offset) != P \
                or len(self.plane_std) != P:
            raise GeometryError("MarkerPriors: the arrays of one kind of measurement must have the same length")
        if np.any(self.distance_std <= 0) or np.any(self.plane_std <= 0):
            raise GeometryError("MarkerPriors: every measurement std must be positive")
        self.relative_marker = np.asarray(self.relative_marker, dtype=int).reshape(-1, 2)
        self.relative_pose = np.asarray(self.relative_pose, dtype=float).reshape(-1, 4, 4)
        self.relative_position_std = np.asarray(self.relative_position_std, dtype=float).reshape(-1)
        self.relative_rotation_std = np.asarray(self.relative_rotation_std, dtype=float).reshape(-1)
        Q = len(self.relative_marker)
        if len(self.relative_pose) != Q or len(self.relative_position_std) != Q \
                or len(self.relative_rotation_std) != Q:
            raise GeometryError("MarkerPriors: the arrays of the relative poses must have the same length")
        if np.any(self.relative_position_std <= 0) or np.any(self.relative_rotation_std <= 0):
            raise GeometryError("MarkerPriors: every relative pose std must be positive")

    @property
    def n_residuals(self) -> int:
        return (3 * len(self.position_marker) + 3 * len(self.rotation_marker) + 2 * len(self.level_station)
                + len(self.distance_marker) + len(self.plane_marker) + 6 * len(self.relative_marker))

    @property
    def n_pose_residuals(self) -> int:
        """Rows before the measurements' (positions, rotations, level stations)."""
        return 3 * len(self.position_marker) + 3 * len(self.rotation_marker) + 2 * len(self.level_station)


@dataclass
class RelativePoseFactors:
    """Measured motions between pairs of stations (odometry): K factors.

    Attributes:
        station_i, station_j: (K,) station indices (the motion goes from i to j).
        T_ij: (K, 4, 4) the measured ``T_W_i^-1 T_W_j`` (the base frame at j seen from i).
        sigma: (K, 6) 1-sigma of the residual: rotation (rad, 3 axes) then translation (m, 3 axes
            of station i's base frame).
        robust_scale: whitened norm beyond which a factor's weight falls as ``robust_scale / norm``
            (Huber): a glitch of the odometry pulls with a bounded force; <= 0: plain least squares.
    """

    station_i: np.ndarray
    station_j: np.ndarray
    T_ij: np.ndarray
    sigma: np.ndarray
    robust_scale: float = 3.0

    def __post_init__(self) -> None:
        self.station_i = np.asarray(self.station_i, dtype=int).reshape(-1)
        self.station_j = np.asarray(self.station_j, dtype=int).reshape(-1)
        self.T_ij = np.asarray(self.T_ij, dtype=float).reshape(-1, 4, 4)
        self.sigma = np.asarray(self.sigma, dtype=float).reshape(-1, 6)
        K = len(self.station_i)
        if len(self.station_j) != K or len(self.T_ij) != K or len(self.sigma) != K:
            raise GeometryError("RelativePoseFactors: station_i, station_j, T_ij and sigma must have the same length")
        if np.any(self.station_i == self.station_j):
            raise GeometryError("RelativePoseFactors: a factor links a station to itself")
        if not np.all(np.isfinite(self.T_ij)) or not np.all(np.isfinite(self.sigma)) or np.any(self.sigma <= 0):
            raise GeometryError("RelativePoseFactors: every motion must be finite and every sigma positive")

    def __len__(self) -> int:
        return len(self.station_i)


@dataclass
class BAProblem:
    """Inputs of :func:`bundle_adjust`. N observations of 4 corners.

    Attributes:
        T_W_markers: (M, 4, 4) initial marker poses.
        sizes: (M,) marker sides, m.
        T_W_stations: (S, 4, 4) initial robot poses.
        T_base_cams: (C, 4, 4) ring extrinsics (calibration).
        obs_marker, obs_station, obs_camera: (N,) indices into the above.
        obs_xy: (N, 4, 2) observed corners, undistorted normalised coordinates.
        obs_focal: (N, 2) focal lengths (fx, fy) in pixels of the camera that saw each.
        fixed_marker: index of the marker held fixed (gauge), or None (then a station must be).
        fixed_station: index of a station held fixed, or None.
        T_base_cams_start: (C, 4, 4) starting extrinsics when they are refined (default: the
            calibration ``T_base_cams``, which stays the centre of their prior).
        obs_lens: optional (N, 4, 2, 2) Jacobian of the raw pixels with respect to the undistorted
            normalised coordinates at each observed corner (:meth:`CameraModel.pixel_jacobian`).
            Given, the residuals are first-order *raw* pixel errors: a wide-angle or fisheye lens
            compresses the image towards its border (a corner 60 deg off-axis moves ~4x fewer raw
            pixels than pinhole pixels), and without it those corners would count as 4x noisier.
            Default: ``diag(obs_focal)``, the ideal pinhole camera.
        priors: optional :class:`MarkerPriors` (surveyed markers, level stations): with them no
            marker or station needs to be fixed.
        odometry: optional :class:`RelativePoseFactors` between stations (the robot's odometry).
        obs_object: optional (N, 4, 3) corners of each observation in its marker's frame (default:
            the square of ``sizes``): one unknown can then be a rigid board of several markers,
            each observation's corners placed by the board's layout (:mod:`boards`).
        extrinsics_sigma: optional (C, 6) prior std of each camera's extrinsics when they are
            refined, rotation (rad) then translation (m), per axis of the base frame (the
            perturbation ``R = exp(w) R0``, ``t = t0 + dt``): a calibration stated per camera (the
            ring file's ``extrinsics_std``); default: ``BAOptions.extrinsics_*_sigma`` for every camera.
        hold_markers: every marker held at ``T_W_markers`` (no marker unknowns; ``fixed_marker`` is
            then moot): the localization setting, the map given and only the stations (and the
            cameras when refined) estimated -- the smoothing of a trajectory on a map
            (:mod:`smoother`). The markers are then the gauge.
    """

    T_W_markers: np.ndarray
    sizes: np.ndarray
    T_W_stations: np.ndarray
    T_base_cams: np.ndarray
    obs_marker: np.ndarray
    obs_station: np.ndarray
    obs_camera: np.ndarray
    obs_xy: np.ndarray
    obs_focal: np.ndarray
    fixed_marker: Optional[int] = 0
    fixed_station: Optional[int] = None
    T_base_cams_start: Optional[np.ndarray] = None
    obs_lens: Optional[np.ndarray] = None
    priors: Optional[MarkerPriors] = None
    odometry: Optional[RelativePoseFactors] = None
    obs_object: Optional[np.ndarray] = None
    extrinsics_sigma: Optional[np.ndarray] = None
    hold_markers: bool = False


@dataclass(frozen=True)
class BAOptions:
    """Solver settings of the bundle adjustment (the mapper's ``mapping.ba`` section, config/mapping.yaml)."""

    pixel_noise: float = param(0.5, "expected 1-sigma corner noise (the residuals are divided by it)", unit="px")
    loss: str = param("huber", "scipy robust loss: huber, soft_l1, cauchy or linear")
    robust_scale: float = param(3.0, "where the loss turns robust, in units of pixel_noise")
    refine_extrinsics: bool = param(False, "also refine each camera's T_base_cam, with the priors below")
    extrinsics_trans_sigma: float = param(0.005, "prior std of the calibrated camera translations", unit="m")
    extrinsics_rot_sigma_deg: float = param(0.5, "prior std of the calibrated camera rotations", unit="deg")
    max_nfev: int = param(200, "solver iteration cap (function evaluations)")
    dense_max_params: int = param(300, "up to this many unknowns the trust-region steps are solved densely "
                                       "(tr_solver exact), above with LSMR on the sparse Jacobian (solver trf)")
    ftol: float = param(1e-8, "solver tolerance on the cost")
    xtol: float = param(1e-10, "solver tolerance on the step")
    gtol: float = param(1e-10, "solver tolerance on the gradient")
    lsmr_tol: float = param(1e-10, "LSMR's atol/btol for the sparse trust-region steps (looser is faster per "
                                   "iteration, enough for quick adjustments of an initialisation)")
    covariance: bool = param(True, "compute per-marker covariances")
    solver: str = param("lm", "lm = Levenberg-Marquardt on the sparse normal equations (direct sparse solve, "
                              "robust loss by iterative reweighting); trf = scipy's trust region with LSMR steps "
                              "(slow to converge on long, weakly coupled problems)")

    extrinsics_rot_sigma = in_radians("extrinsics_rot_sigma_deg")

    def __post_init__(self) -> None:
        if self.loss not in ("huber", "soft_l1", "cauchy", "linear", "arctan"):
            raise ConfigError(f"expected huber, soft_l1, cauchy, arctan or linear, got {self.loss!r}", key="loss")
        if self.solver not in ("lm", "trf"):
            raise ConfigError(f"expected lm or trf, got {self.solver!r}", key="solver")
        require_positive(self, "pixel_noise", "robust_scale", "extrinsics_trans_sigma", "extrinsics_rot_sigma_deg")


@dataclass
class BAResult:
    """Outputs of :func:`bundle_adjust`.

    Attributes:
        T_W_markers, T_W_stations, T_base_cams: refined poses (same shapes as the problem's).
        marker_cov: (M, 6, 6) covariance of (w, t) per marker (w rotation in W, rad; t in W, m);
            zeros for the fixed marker. None when not computed.
        camera_cov: (6C, 6C) covariance of the cameras' (w, t) (``R = exp(w) R0``, ``t = t0 + t``,
            in the base frame) when the extrinsics are refined and covariances computed, else None.
        rms_px_before, rms_px_after: RMS corner reprojection error (px, undistorted).
        per_obs_rms_px: (N,) RMS error per observation after the refinement, px.
        variance_factor: residual variance / pixel_noise^2 (≈ (true noise / pixel_noise)^2).
        seconds: solver wall time (covariance included); nfev: evaluations; status: scipy's message.
        cpu_seconds: the same span as CPU time of the process (utime + stime): on a loaded
            machine the wall time measures the queue, this the work.
    """

    T_W_markers: np.ndarray
    T_W_stations: np.ndarray
    T_base_cams: np.ndarray
    marker_cov: Optional[np.ndarray]
    rms_px_before: float
    rms_px_after: float
    per_obs_rms_px: np.ndarray
    variance_factor: float
    seconds: float
    nfev: int
    status: str
    n_residuals: int = 0
    n_params: int = 0
    extra: Dict[str, float] = field(default_factory=dict)
    camera_cov: Optional[np.ndarray] = None
    cpu_seconds: float = 0.0


# --- the problem as residual + Jacobian functions -----------------------------------------------

class _Model:
    """Parameter layout, residuals and the analytic sparse Jacobian."""

    def __init__(self, prob: BAProblem, opts: BAOptions):
        self.p = prob
        self.o = opts
        M, S, C = len(prob.T_W_markers), len(prob.T_W_stations), len(prob.T_base_cams)
        N = len(prob.obs_marker)
        if N == 0:
            raise GeometryError("bundle adjustment needs at least one observation")
        priors = prob.priors if prob.priors is not None and prob.priors.n_residuals else None
        if prob.fixed_marker is None and prob.fixed_station is None and not opts.refine_extrinsics and priors is None \
                and not prob.hold_markers:
            raise GeometryError("bundle adjustment needs a gauge: a fixed marker, a fixed station or priors")
        self.priors = priors
        self.M, self.S, self.C, self.N = M, S, C, N
        # Column offset of each pose block; -1 for fixed ones.
        self.col_m = np.full(M, -1)
        self.col_s = np.full(S, -1)
        self.col_c = np.full(C, -1)
        col = 0
        for i in range(M):
            if i != prob.fixed_marker and not prob.hold_markers:
                self.col_m[i] = col
                col += 6
        self.n_marker_params = col
        for i in range(S):
            if i != prob.fixed_station:
                self.col_s[i] = col
                col += 6
        if opts.refine_extrinsics:
            for i in range(C):
                self.col_c[i] = col
                col += 6
        self.n_params = col
        self.R_m0 = prob.T_W_markers[:, :3, :3].copy()
        self.t_m0 = prob.T_W_markers[:, :3, 3].copy()
        self.R_s0 = prob.T_W_stations[:, :3, :3].copy()
        self.t_s0 = prob.T_W_stations[:, :3, 3].copy()
        self.R_c0 = prob.T_base_cams[:, :3, :3].copy()
        self.t_c0 = prob.T_base_cams[:, :3, 3].copy()
        # Corner coordinates in the marker frame, per observation: (N, 4, 3).
        if prob.obs_object is not None:
            self.X = np.asarray(prob.obs_object, dtype=float).reshape(N, 4, 3)
        else:
            unit = marker_corners(1.0)
            self.X = unit[None, :, :] * np.asarray(prob.sizes, dtype=float)[prob.obs_marker][:, None, None]
        if prob.obs_lens is not None:
            self.A = np.asarray(prob.obs_lens, dtype=float) / opts.pixel_noise     # (N, 4, 2, 2)
        else:
            self.A = np.zeros((N, 4, 2, 2))
            self.A[..., 0, 0] = (prob.obs_focal[:, 0] / opts.pixel_noise)[:, None]
            self.A[..., 1, 1] = (prob.obs_focal[:, 1] / opts.pixel_noise)[:, None]
        self.n_obs_res = 8 * N
        self.n_prior_res = 6 * C if opts.refine_extrinsics else 0
        # Prior std of each camera's (w, t): the problem's per camera, else the options' for all.
        if prob.extrinsics_sigma is not None:
            sig = np.asarray(prob.extrinsics_sigma, dtype=float)
            if sig.shape != (C, 6) or not np.all(np.isfinite(sig)) or np.any(sig <= 0):
                raise GeometryError(f"bundle adjustment: extrinsics_sigma must be ({C}, 6) positive numbers, got "
                                    f"shape {sig.shape}")
            self.ext_sigma = sig
        else:
            self.ext_sigma = np.tile(np.r_[np.full(3, opts.extrinsics_rot_sigma),
                                           np.full(3, opts.extrinsics_trans_sigma)], (C, 1))
        self.n_anchor_res = priors.n_residuals if priors is not None else 0
        if priors is not None:
            if np.any(self.col_m[priors.position_marker] < 0) or np.any(self.col_m[priors.rotation_marker] < 0) \
                    or np.any(self.col_s[priors.level_station] < 0):
                raise GeometryError("bundle adjustment: a prior on a fixed marker or station (leave it free)")
        odo = prob.odometry if prob.odometry is not None and len(prob.odometry) else None
        if odo is not None and (np.any(odo.station_i < 0) or np.any(odo.station_i >= S) or np.any(odo.station_j < 0)
                                or np.any(odo.station_j >= S)):
            raise GeometryError("bundle adjustment: an odometry factor names a station that does not exist")
        self.odo = odo
        self.n_odo_res = 6 * len(odo) if odo is not None else 0
        self.n_res = self.n_obs_res + self.n_prior_res + self.n_anchor_res + self.n_odo_res
        # Measured distances between two free markers couple them: the markers' block of H is then
        # no longer block diagonal, and the steps eliminating the markers add the distance rows
        # back exactly (Woodbury, :meth:`solve_damped`).
        D = len(priors.distance_marker) if priors is not None else 0
        self._dist_rows = (self.n_obs_res + self.n_prior_res + (priors.n_pose_residuals if D else 0)
                           + np.arange(D))
        if D:
            ca, cb = self.col_m[priors.distance_marker[:, 0]], self.col_m[priors.distance_marker[:, 1]]
            self._dist_coupled = bool(np.any((ca >= 0) & (cb >= 0) & (ca != cb)))
        else:
            self._dist_coupled = False
        # Relative poses (tags loose on a board) couple markers too, 6 rows each: the markers'
        # block of H is then solved as a sparse matrix (:meth:`_solve_markers_coupled`).
        if priors is not None and len(priors.relative_marker):
            ca, cb = self.col_m[priors.relative_marker[:, 0]], self.col_m[priors.relative_marker[:, 1]]
            self._rel_coupled = bool(np.any((ca >= 0) & (cb >= 0) & (ca != cb)))
        else:
            self._rel_coupled = False
        self._build_pattern()

    def _build_pattern(self) -> None:
        """Row/column indices of the Jacobian's non-zeros (fixed pattern)."""
        N = self.N
        rows = np.arange(8 * N).reshape(N, 4, 2)
        blocks = [self.col_m[self.p.obs_marker], self.col_s[self.p.obs_station]]
        if self.o.refine_extrinsics:
            blocks.append(self.col_c[self.p.obs_camera])
        r_list, c_list, mask_list = [], [], []
        for cols in blocks:
            # For each residual row, 6 columns cols..cols+5.
            rr = np.broadcast_to(rows[..., None], (N, 4, 2, 6))
            cc = np.broadcast_to(cols[:, None, None, None] + np.arange(6), (N, 4, 2, 6))
            valid = np.broadcast_to((cols >= 0)[:, None, None, None], (N, 4, 2, 6))
            r_list.append(rr)
            c_list.append(cc)
            mask_list.append(valid)
        self._blk_rows = [r[m] for r, m in zip(r_list, mask_list)]
        self._blk_cols = [c[m] for c, m in zip(c_list, mask_list)]
        self._blk_masks = mask_list
        if self.n_prior_res:
            pr = self.n_obs_res + np.arange(6 * self.C)
            pc = np.concatenate([self.col_c[i] + np.arange(6) for i in range(self.C)])
            self._prior_rows, self._prior_cols = pr, pc
        extra_r = [self._prior_rows] if self.n_prior_res else []
        extra_c = [self._prior_cols] if self.n_prior_res else []
        if self.n_anchor_res:
            ar, ac = self._anchor_pattern(self.n_obs_res + self.n_prior_res)
            extra_r.append(ar)
            extra_c.append(ac)
        if self.n_odo_res:
            orr, occ = self._odometry_pattern(self.n_obs_res + self.n_prior_res + self.n_anchor_res)
            extra_r.append(orr)
            extra_c.append(occ)
        self.rows = np.concatenate(self._blk_rows + extra_r)
        self.cols = np.concatenate(self._blk_cols + extra_c)

    def _anchor_pattern(self, base: int) -> Tuple[np.ndarray, np.ndarray]:
        """Rows/columns of the prior block (positions 3x3 diagonal on t, rotations 3x3 full on w,
        level 2x3 on the station's w), in the order :meth:`_anchor_residuals` gives them."""
        pr = self.priors
        rows, cols = [], []
        K, L, J = len(pr.position_marker), len(pr.rotation_marker), len(pr.level_station)
        rows.append(base + np.arange(3 * K))
        cols.append((self.col_m[pr.position_marker][:, None] + 3 + np.arange(3)).ravel())
        base += 3 * K
        r = base + 3 * np.arange(L)[:, None, None] + np.arange(3)[None, :, None]
        c = self.col_m[pr.rotation_marker][:, None, None] + np.arange(3)[None, None, :]
        rows.append(np.broadcast_to(r, (L, 3, 3)).ravel())
        cols.append(np.broadcast_to(c, (L, 3, 3)).ravel())
        base += 3 * L
        r = base + 2 * np.arange(J)[:, None, None] + np.arange(2)[None, :, None]
        c = self.col_s[pr.level_station][:, None, None] + np.arange(3)[None, None, :]
        rows.append(np.broadcast_to(r, (J, 2, 3)).ravel())
        cols.append(np.broadcast_to(c, (J, 2, 3)).ravel())
        base += 2 * J
        # Distances: 1 row x (w, t of marker a, then of marker b); planes: 1 row x (w, t) of the
        # marker; the columns of a fixed marker left out (masks kept for the values).
        D, P = len(pr.distance_marker), len(pr.plane_marker)
        ca, cb = self.col_m[pr.distance_marker[:, 0]], self.col_m[pr.distance_marker[:, 1]]
        c = np.concatenate([ca[:, None] + np.arange(6), cb[:, None] + np.arange(6)], axis=1)
        self._dist_mask = np.concatenate([np.repeat((ca >= 0)[:, None], 6, 1), np.repeat((cb >= 0)[:, None], 6, 1)],
                                         axis=1)
        rows.append(np.broadcast_to((base + np.arange(D))[:, None], (D, 12))[self._dist_mask])
        cols.append(c[self._dist_mask])
        base += D
        cp = self.col_m[pr.plane_marker]
        self._plane_mask = np.repeat((cp >= 0)[:, None], 6, 1)
        rows.append(np.broadcast_to((base + np.arange(P))[:, None], (P, 6))[self._plane_mask])
        cols.append((cp[:, None] + np.arange(6))[self._plane_mask])
        base += P
        # Relative poses: 6 rows x (w, t of marker a, then of marker b), as the distances.
        Q = len(pr.relative_marker)
        ca, cb = self.col_m[pr.relative_marker[:, 0]], self.col_m[pr.relative_marker[:, 1]]
        free = np.concatenate([np.repeat((ca >= 0)[:, None], 6, 1), np.repeat((cb >= 0)[:, None], 6, 1)], axis=1)
        self._rel_mask = np.broadcast_to(free[:, None, :], (Q, 6, 12))
        c = np.concatenate([ca[:, None] + np.arange(6), cb[:, None] + np.arange(6)], axis=1)[:, None, :]
        r = base + 6 * np.arange(Q)[:, None, None] + np.arange(6)[None, :, None]
        rows.append(np.broadcast_to(r, (Q, 6, 12))[self._rel_mask])
        cols.append(np.broadcast_to(c, (Q, 6, 12))[self._rel_mask])
        return np.concatenate(rows).astype(int), np.concatenate(cols).astype(int)

    def _odometry_pattern(self, base: int) -> Tuple[np.ndarray, np.ndarray]:
        """Rows/columns of the odometry block: per factor 6 rows x the 12 columns (w, t of station
        i, then of station j), the columns of a fixed station left out (``self._odo_mask``)."""
        K = len(self.odo)
        rows = base + 6 * np.arange(K)[:, None, None] + np.arange(6)[None, :, None]
        ci, cj = self.col_s[self.odo.station_i], self.col_s[self.odo.station_j]
        cols = np.concatenate([ci[:, None] + np.arange(6), cj[:, None] + np.arange(6)], axis=1)[:, None, :]
        free = np.concatenate([np.repeat((ci >= 0)[:, None], 6, 1), np.repeat((cj >= 0)[:, None], 6, 1)], axis=1)
        self._odo_mask = np.broadcast_to(free[:, None, :], (K, 6, 12))
        rows = np.broadcast_to(rows, (K, 6, 12))
        cols = np.broadcast_to(cols, (K, 6, 12))
        return rows[self._odo_mask].astype(int), cols[self._odo_mask].astype(int)

    def _odometry_residuals(self, ws, Rs, ts, jacobian: bool = False):
        """The odometry rows (whitened), and with ``jacobian`` their (K, 6, 12) Jacobian (columns
        w_i, t_i, w_j, t_j) masked to the pattern's order.

        ``e_R = log(R_z^T R_i^T R_j)``, ``e_t = R_i^T (t_j - t_i) - t_z``. With ``R = exp(w) R0``:
        ``de_R/dw_j = J_l(e_R)^-1 R_z^T R_i^T J_l(w_j)`` and ``de_R/dw_i`` its negative with
        ``J_l(w_i)``; ``de_t/dw_i = R0_i^T [exp(-w_i) (t_j - t_i)]x J_l(-w_i)``, ``de_t/dt_i = -R_i^T``,
        ``de_t/dt_j = R_i^T``.
        """
        o = self.odo
        i, j = o.station_i, o.station_j
        Rz, tz = o.T_ij[:, :3, :3], o.T_ij[:, :3, 3]
        RiT = np.transpose(Rs[i], (0, 2, 1))
        A = np.transpose(Rz, (0, 2, 1)) @ RiT                          # R_z^T R_i^T
        eR = Rotation.from_matrix(A @ Rs[j]).as_rotvec()
        q = ts[j] - ts[i]
        et = (RiT @ q[:, :, None])[..., 0] - tz
        r = (np.concatenate([eR, et], axis=1) / o.sigma).ravel()
        if not jacobian:
            return r
        K = len(o)
        Jinv = np.linalg.inv(geo.so3_left_jacobian(eR))
        JA = Jinv @ A
        Jm = np.zeros((K, 6, 12))
        Jm[:, :3, 0:3] = -JA @ geo.so3_left_jacobian(ws[i])
        Jm[:, :3, 6:9] = JA @ geo.so3_left_jacobian(ws[j])
        Einv = Rotation.from_rotvec(-ws[i]).as_matrix()
        u = (Einv @ q[:, :, None])[..., 0]
        Jm[:, 3:, 0:3] = np.transpose(self.R_s0[i], (0, 2, 1)) @ (geo.skew(u) @ geo.so3_left_jacobian(-ws[i]))
        Jm[:, 3:, 3:6] = -RiT
        Jm[:, 3:, 9:12] = RiT
        Jm /= o.sigma[:, :, None]
        return r, Jm[self._odo_mask]

    def odometry_weights(self, r: np.ndarray) -> np.ndarray:
        """(n_odo_res,) IRLS weights of the odometry rows of residuals ``r`` (Huber on each factor's
        whitened norm, the same weight for its 6 rows)."""
        ro = r[self.n_res - self.n_odo_res:].reshape(-1, 6)
        c = self.odo.robust_scale
        if c <= 0:
            return np.ones(ro.size)
        n = np.linalg.norm(ro, axis=1)
        return np.repeat(np.where(n <= c, 1.0, c / np.maximum(n, 1e-300)), 6)

    def odometry_cost(self, r: np.ndarray) -> float:
        """sum of the Huber losses ``rho(|r_k|)`` of the odometry factors (``|r_k|^2`` inside the scale)."""
        if not self.n_odo_res:
            return 0.0
        n = np.linalg.norm(r[self.n_res - self.n_odo_res:].reshape(-1, 6), axis=1)
        c = self.odo.robust_scale
        if c <= 0:
            return float(np.sum(n * n))
        return float(np.sum(np.where(n <= c, n * n, 2.0 * c * n - c * c)))

    def _anchor_residuals(self, wm, Rm, tm, ws, Rs, jacobian: bool = False):
        """The prior residuals (and with ``jacobian`` their Jacobian's non-zeros, pattern order)."""
        pr = self.priors
        im, il, js = pr.position_marker, pr.rotation_marker, pr.level_station
        # Position: r = (t_m - p) / std, dr/dt = 1 / std.
        r = [((tm[im] - pr.position) / pr.position_std).ravel()]
        d = [(1.0 / pr.position_std).ravel()]
        # Orientation: r = log(R_m R_s^T) / std; with R_m = exp(w) R0, dr/dw = J_l(r)^-1 J_l(w) / std.
        if len(il):
            phi = Rotation.from_matrix(Rm[il] @ np.transpose(pr.rotation, (0, 2, 1))).as_rotvec()
            r.append((phi / pr.rotation_std[:, None]).ravel())
            if jacobian:
                Jr = np.linalg.inv(geo.so3_left_jacobian(phi)) @ geo.so3_left_jacobian(wm[il])
                d.append((Jr / pr.rotation_std[:, None, None]).ravel())
        # Level station: r = (z_x, z_y) / sigma of its z axis z = R_s e_z; dz/dv = -[z]x J_l(v).
        if len(js):
            z = Rs[js][:, :, 2]
            r.append((z[:, :2] / pr.level_sigma).ravel())
            if jacobian:
                dz = -(geo.skew(z) @ geo.so3_left_jacobian(ws[js]))[:, :2, :]
                d.append((dz / pr.level_sigma).ravel())
        # Distance: p = R_m X + t_m per end, r = (|p_a - p_b| - L) / std; with u = (p_a - p_b) / |.|,
        # dr/d(w_a, t_a) = u^T (-[R_a X_a]x J_l(w_a), I) / std and the negative for marker b.
        if len(pr.distance_marker):
            ia, ib = pr.distance_marker[:, 0], pr.distance_marker[:, 1]
            va = (Rm[ia] @ pr.distance_point[:, 0, :, None])[..., 0]
            vb = (Rm[ib] @ pr.distance_point[:, 1, :, None])[..., 0]
            diff = (va + tm[ia]) - (vb + tm[ib])
            length = np.maximum(np.linalg.norm(diff, axis=1), 1e-12)
            r.append((length - pr.distance) / pr.distance_std)
            if jacobian:
                u = (diff / length[:, None])[:, None, :]                              # (D, 1, 3)
                ja = (u @ (-geo.skew(va) @ geo.so3_left_jacobian(wm[ia])))[:, 0, :]
                jb = (u @ (-geo.skew(vb) @ geo.so3_left_jacobian(wm[ib])))[:, 0, :]
                Jd = np.concatenate([ja, u[:, 0, :], -jb, -u[:, 0, :]], axis=1) / pr.distance_std[:, None]
                d.append(Jd[self._dist_mask])
        # Plane: r = (n . (R_m X + t_m) - offset) / std, dr/d(w, t) = n^T (-[R_m X]x J_l(w), I) / std.
        if len(pr.plane_marker):
            ip = pr.plane_marker
            v = (Rm[ip] @ pr.plane_point[:, :, None])[..., 0]
            n = pr.plane_normal
            r.append((np.sum(n * (v + tm[ip]), axis=1) - pr.plane_offset) / pr.plane_std)
            if jacobian:
                jw = (n[:, None, :] @ (-geo.skew(v) @ geo.so3_left_jacobian(wm[ip])))[:, 0, :]
                Jp = np.concatenate([jw, n], axis=1) / pr.plane_std[:, None]
                d.append(Jp[self._plane_mask])
        # Relative pose of b in a: e_R = log(Z^T R_a^T R_b), e_t = R_a^T (t_b - t_a) - t_z. With
        # R = exp(w) R0: de_R/dw_b = J_l(e_R)^-1 Z^T R_a^T J_l(w_b), de_R/dw_a its negative with
        # J_l(w_a); de_t/dw_a = R_a^T [t_b - t_a]x J_l(w_a), de_t/dt_a = -R_a^T, de_t/dt_b = R_a^T.
        if len(pr.relative_marker):
            ia, ib = pr.relative_marker[:, 0], pr.relative_marker[:, 1]
            Z = pr.relative_pose
            RaT = np.transpose(Rm[ia], (0, 2, 1))
            A = np.transpose(Z[:, :3, :3], (0, 2, 1)) @ RaT
            eR = Rotation.from_matrix(A @ Rm[ib]).as_rotvec()
            q = tm[ib] - tm[ia]
            et = (RaT @ q[:, :, None])[..., 0] - Z[:, :3, 3]
            sig = np.concatenate([np.repeat(pr.relative_rotation_std[:, None], 3, 1),
                                  np.repeat(pr.relative_position_std[:, None], 3, 1)], axis=1)
            r.append((np.concatenate([eR, et], axis=1) / sig).ravel())
            if jacobian:
                JA = np.linalg.inv(geo.so3_left_jacobian(eR)) @ A
                Jq = np.zeros((len(ia), 6, 12))
                Jq[:, :3, 0:3] = -JA @ geo.so3_left_jacobian(wm[ia])
                Jq[:, :3, 6:9] = JA @ geo.so3_left_jacobian(wm[ib])
                Jq[:, 3:, 0:3] = RaT @ geo.skew(q) @ geo.so3_left_jacobian(wm[ia])
                Jq[:, 3:, 3:6] = -RaT
                Jq[:, 3:, 9:12] = RaT
                Jq /= sig[:, :, None]
                d.append(Jq[self._rel_mask])
        return (np.concatenate(r), np.concatenate(d)) if jacobian else np.concatenate(r)

    def sparsity(self) -> sp.csr_matrix:
        return sp.csr_matrix((np.ones(len(self.rows)), (self.rows, self.cols)), shape=(self.n_res, self.n_params))

    def _unpack(self, x: np.ndarray, col: np.ndarray, R0: np.ndarray, t0: np.ndarray):
        w = np.zeros((len(col), 3))
        dt = np.zeros((len(col), 3))
        free = col >= 0
        if np.any(free):
            blocks = x[col[free][:, None] + np.arange(6)]
            w[free] = blocks[:, :3]
            dt[free] = blocks[:, 3:]
        E = Rotation.from_rotvec(w).as_matrix()
        return w, E @ R0, t0 + dt, E

    def poses(self, x: np.ndarray):
        """Current (R, t) of markers, stations, cameras, plus the rotation vectors."""
        wm, Rm, tm, _ = self._unpack(x, self.col_m, self.R_m0, self.t_m0)
        ws, Rs, ts, Es = self._unpack(x, self.col_s, self.R_s0, self.t_s0)
        wc, Rc, tc, Ec = self._unpack(x, self.col_c, self.R_c0, self.t_c0)
        return (wm, Rm, tm), (ws, Rs, ts, Es), (wc, Rc, tc, Ec)

    def _forward(self, x: np.ndarray):
        (wm, Rm, tm), (ws, Rs, ts, Es), (wc, Rc, tc, Ec) = self.poses(x)
        im, is_, ic = self.p.obs_marker, self.p.obs_station, self.p.obs_camera
        a = self.X @ np.transpose(Rm[im], (0, 2, 1))                 # R_m X, (N, 4, 3)
        pW = a + tm[im][:, None, :]
        q = pW - ts[is_][:, None, :]                                  # p_W - t_s
        pb = q @ Rs[is_]                                              # R_s^T q
        q2 = pb - tc[ic][:, None, :]
        pc = q2 @ Rc[ic]                                              # R_c^T q2
        return (wm, Rm, tm), (ws, Rs, ts, Es), (wc, Rc, tc, Ec), a, q, q2, pc

    def residuals(self, x: np.ndarray) -> np.ndarray:
        (wm, Rm, tm), (ws, Rs, ts, _), _, _, _, _, pc = self._forward(x)
        z = pc[..., 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        proj = pc[..., :2] / z[..., None]
        r = (self.A @ (proj - self.p.obs_xy)[..., None])[..., 0]
        out = r.ravel()
        if self.n_prior_res:
            prior = x[self._prior_cols].reshape(self.C, 6) / self.ext_sigma
            out = np.concatenate([out, prior.ravel()])
        if self.n_anchor_res:
            out = np.concatenate([out, self._anchor_residuals(wm, Rm, tm, ws, Rs)])
        if self.n_odo_res:
            out = np.concatenate([out, self._odometry_residuals(ws, Rs, ts)])
        return out

    def _jacobian_blocks(self, x: np.ndarray):
        """The Jacobian's non-zeros: per observation one (N, 8, 6) block per pose kind (marker,
        station, camera when refined; rows = the 4 corners x (u, v), fixed poses included) and the
        prior rows' values in pattern order (or None)."""
        (wm, Rm, tm), (ws, Rs, ts, Es), (wc, Rc, tc, Ec), a, q, q2, pc = self._forward(x)
        im, is_, ic = self.p.obs_marker, self.p.obs_station, self.p.obs_camera
        N = self.N
        z = pc[..., 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        # d(scaled projection)/d p_c: (N, 4, 2, 3)
        D = np.zeros(pc.shape[:2] + (2, 3))
        D[..., 0, 0] = 1.0 / z
        D[..., 1, 1] = 1.0 / z
        D[..., 0, 2] = -pc[..., 0] / z ** 2
        D[..., 1, 2] = -pc[..., 1] / z ** 2
        D = self.A @ D
        RcT = np.transpose(Rc[ic], (0, 2, 1))                         # (N, 3, 3)
        RsT = np.transpose(Rs[is_], (0, 2, 1))
        DRc = D @ RcT[:, None]                                        # d r / d p_b, (N, 4, 2, 3)
        DRcRs = DRc @ RsT[:, None]                                    # d r / d p_W
        blocks = []
        # Marker: dp_W/dw = -[R_m X]x J_l(w_m), dp_W/dt = I.
        Jl_m = geo.so3_left_jacobian(wm)[im]                         # (N, 3, 3)
        dpw_dw = -(geo.skew(a) @ Jl_m[:, None])                      # (N, 4, 3, 3)
        blocks.append(np.concatenate([DRcRs @ dpw_dw, DRcRs], axis=-1).reshape(N, 8, 6))
        # Station: dp_b/dv = R_s0^T [exp(-v) q]x J_l(-v), dp_b/dt_s = -R_s^T.
        Einv = np.transpose(Es, (0, 2, 1))[is_]                        # exp(-v)
        Jl_s = geo.so3_left_jacobian(-ws)[is_]
        u = q @ np.transpose(Einv, (0, 2, 1))
        R0T = np.transpose(self.R_s0[is_], (0, 2, 1))
        dpb_dv = R0T[:, None] @ (geo.skew(u) @ Jl_s[:, None])
        blocks.append(np.concatenate([DRc @ dpb_dv, -DRcRs], axis=-1).reshape(N, 8, 6))
        if self.o.refine_extrinsics:
            Einv_c = np.transpose(Ec, (0, 2, 1))[ic]
            Jl_c = geo.so3_left_jacobian(-wc)[ic]
            u2 = q2 @ np.transpose(Einv_c, (0, 2, 1))
            Rc0T = np.transpose(self.R_c0[ic], (0, 2, 1))
            dpc_de = Rc0T[:, None] @ (geo.skew(u2) @ Jl_c[:, None])
            blocks.append(np.concatenate([D @ dpc_de, -DRc], axis=-1).reshape(N, 8, 6))
        extra = []
        if self.n_prior_res:
            extra.append((1.0 / self.ext_sigma).ravel())
        if self.n_anchor_res:
            extra.append(self._anchor_residuals(wm, Rm, tm, ws, Rs, jacobian=True)[1])
        if self.n_odo_res:
            extra.append(self._odometry_residuals(ws, Rs, ts, jacobian=True)[1])
        return blocks, (np.concatenate(extra) if extra else None)

    def jacobian(self, x: np.ndarray) -> sp.csr_matrix:
        """The (n_res, n_params) Jacobian of :meth:`residuals`, sparse."""
        blocks, extra = self._jacobian_blocks(x)
        data = [b.reshape(self.N, 4, 2, 6)[m] for b, m in zip(blocks, self._blk_masks)]
        if extra is not None:
            data.append(extra)
        return sp.csr_matrix((np.concatenate(data), (self.rows, self.cols)), shape=(self.n_res, self.n_params))

    # --- normal equations ---------------------------------------------------------------------

    def _build_normal_pattern(self) -> None:
        """The fixed CSR structure of ``H = J^T W J`` and where every product lands in it.

        Observation n touches the K = 12 (18 with the cameras) columns of its marker, station (and
        camera): its (K, K) block ``J_n^T W_n J_n`` is scattered into H by one ``bincount`` over
        precomputed positions, which is what makes an iteration cheap (no sparse product of the
        whole Jacobian). The prior rows' small ``J_e^T J_e`` is added into the same structure.
        """
        N, n = self.N, self.n_params
        starts = [self.col_m[self.p.obs_marker], self.col_s[self.p.obs_station]]
        if self.o.refine_extrinsics:
            starts.append(self.col_c[self.p.obs_camera])
        gcol = np.concatenate([st[:, None] + np.arange(6) for st in starts], axis=1).astype(np.int64)   # (N, K)
        valid = np.concatenate([np.repeat((st >= 0)[:, None], 6, axis=1) for st in starts], axis=1)
        K = gcol.shape[1]
        self._g_valid = valid
        self._g_cols = gcol[valid]
        pair = valid[:, :, None] & valid[:, None, :]
        self._h_pair = pair
        lin = [(np.broadcast_to(gcol[:, :, None], (N, K, K)) * n + np.broadcast_to(gcol[:, None, :], (N, K, K)))[pair]]
        n_obs_lin = len(lin[0])
        n_extra = self.n_prior_res + self.n_anchor_res + self.n_odo_res
        if n_extra:
            k0 = sum(len(r) for r in self._blk_rows)
            self._extra_rows = self.rows[k0:] - self.n_obs_res
            self._extra_cols = self.cols[k0:]
            pat = sp.csr_matrix((np.ones(len(self._extra_rows)), (self._extra_rows, self._extra_cols)),
                                shape=(n_extra, n))
            he = (pat.T @ pat).tocoo()
            lin.append(he.row.astype(np.int64) * n + he.col)
        # Every free pose's own 6x6 block (the damping and the Schur complement read them).
        free = np.concatenate([c[c >= 0] for c in (self.col_m, self.col_s, self.col_c)]).astype(np.int64)
        blk = free[:, None, None] + np.arange(6)
        lin.append((np.broadcast_to(blk, (len(free), 6, 6)) * n
                    + np.broadcast_to(np.transpose(blk, (0, 2, 1)), (len(free), 6, 6))).ravel())
        uniq, inv = np.unique(np.concatenate(lin), return_inverse=True)
        self._h_uniq = uniq
        self._h_obs_pos = inv[:n_obs_lin]
        self._h_indices = (uniq % n).astype(np.int32)
        self._h_indptr = np.searchsorted(uniq // n, np.arange(n + 1)).astype(np.int32)
        self._h_diag = np.searchsorted(uniq, np.arange(n, dtype=np.int64) * (n + 1))
        cm = self.col_m[self.col_m >= 0].astype(np.int64)
        mb = cm[:, None, None] + np.arange(6)
        self._h_marker_blocks = np.searchsorted(uniq, np.broadcast_to(mb, (len(cm), 6, 6)) * n
                                                + np.broadcast_to(np.transpose(mb, (0, 2, 1)), (len(cm), 6, 6)))

    def normal_equations(self, x: np.ndarray, r: np.ndarray, w: np.ndarray) -> Tuple[sp.csr_matrix, np.ndarray]:
        """``H = J^T diag(w) J`` (CSR, :meth:`_build_normal_pattern`'s structure) and ``g = J^T diag(w) r``
        at ``x``, with ``r`` the residuals there and ``w`` (n_res,) the row weights."""
        if not hasattr(self, "_h_uniq"):
            self._build_normal_pattern()
        n, N = self.n_params, self.N
        blocks, extra = self._jacobian_blocks(x)
        sw = np.sqrt(w[: self.n_obs_res]).reshape(N, 8, 1)
        Jw = np.concatenate(blocks, axis=2) * sw                        # (N, 8, K)
        JwT = np.transpose(Jw, (0, 2, 1))
        data = np.bincount(self._h_obs_pos, weights=(JwT @ Jw)[self._h_pair], minlength=len(self._h_uniq))
        gn = (JwT @ (sw * r[: self.n_obs_res].reshape(N, 8, 1)))[..., 0]   # (N, K)
        g = np.bincount(self._g_cols, weights=gn[self._g_valid], minlength=n)
        if extra is not None:
            swe = np.sqrt(w[self.n_obs_res:])
            JE = sp.csr_matrix((extra * swe[self._extra_rows], (self._extra_rows, self._extra_cols)),
                               shape=(self.n_res - self.n_obs_res, n))
            he = (JE.T @ JE).tocoo()
            pos = np.searchsorted(self._h_uniq, he.row.astype(np.int64) * n + he.col)
            data += np.bincount(pos, weights=he.data, minlength=len(self._h_uniq))
            g += JE.T @ (swe * r[self.n_obs_res:])
            if self._dist_coupled:
                # The (weighted) distance rows of this H, for solve_damped's exact correction.
                self._dist_E = JE[self._dist_rows - self.n_obs_res].tocsr()
        return sp.csr_matrix((data, self._h_indices, self._h_indptr), shape=(n, n)), g

    def without_distances(self, H: sp.csr_matrix, E: sp.csr_matrix) -> sp.csr_matrix:
        """``H - E^T E`` in ``H``'s structure (:meth:`normal_equations`'), ``E`` the weighted rows
        of the measured distances: the information without them, whose markers' part is block
        diagonal again."""
        n = self.n_params
        ete = (E.T @ E).tocoo()
        pos = np.searchsorted(self._h_uniq, ete.row.astype(np.int64) * n + ete.col)
        out = H.copy()
        out.data = out.data - np.bincount(pos, weights=ete.data, minlength=len(self._h_uniq))
        return out

    def solve_damped(self, H: sp.csr_matrix, b: np.ndarray, damping: np.ndarray) -> np.ndarray:
        """``(H + diag(damping)) dx = b`` by the Schur complement on the markers.

        Markers only couple to stations and cameras: the markers' part ``A`` of H is block
        diagonal (6x6 each), inverted block by block; the reduced system ``S = C - B^T A^-1 B``
        over the stations and cameras (a band along a chain of stations, plus the cameras) is
        small and sparse (SuperLU). A direct solve of the whole H (as before) factorised the
        markers' columns too: 0.8 s per step for the 1,000-marker hall, against ~0.05 s here.

        Raises:
            RuntimeError: a singular block or reduced system (the caller damps harder).
        """
        from scipy.sparse.linalg import splu

        n, nm = self.n_params, self.n_marker_params
        Hd = H.copy()
        Hd.data[self._h_diag] += damping
        if self._station_elimination():
            try:
                solve, Bd, C, keep, elim = self._reduce_on_stations(Hd)
            except np.linalg.LinAlgError as e:
                raise RuntimeError("singular stations' block") from e
            Z = solve(np.column_stack([Bd, b[elim]]))
            AB, y = Z[:, :-1], Z[:, -1]
            xk = _dense_spd_solve(C - Bd.T @ AB, b[keep] - Bd.T @ y)
            x = np.empty(n)
            x[keep] = xk
            x[elim] = y - AB @ xk
            return x
        if nm == 0:
            return splu(Hd.tocsc()).solve(b)
        if self._rel_coupled:
            return self._solve_markers_coupled(Hd, b)
        if self._dist_coupled:
            # Distances couple markers, which the elimination below (block by block) cannot see:
            # solve without them (H0 = H - E^T E, block diagonal again) and add them back exactly,
            # (H0 + E^T E)^-1 b = y - Z (I + E Z)^-1 E y with y = H0^-1 b, Z = H0^-1 E^T.
            E = self._dist_E
            Y = self._solve_markers_eliminated(self.without_distances(Hd, E), np.column_stack([b, E.T.toarray()]))
            y, Z = Y[:, 0], Y[:, 1:]
            return y - Z @ np.linalg.solve(np.eye(Z.shape[1]) + E @ Z, E @ y)
        return self._solve_markers_eliminated(Hd, b)

    def _solve_markers_eliminated(self, Hd: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        """``Hd x = b`` (``b``: (n,) or (n, k)) through the Schur complement on the markers (their
        6x6 diagonal blocks of ``Hd``; anything between two markers is not read)."""
        from scipy.sparse.linalg import splu

        n, nm = self.n_params, self.n_marker_params
        shape = b.shape
        b = b.reshape(n, -1)
        k = b.shape[1]
        A = Hd.data[self._h_marker_blocks]                               # (Mf, 6, 6)
        try:
            Ainv = np.linalg.inv(A)
        except np.linalg.LinAlgError as e:
            raise RuntimeError("singular marker block") from e
        Mf = len(A)
        y = (Ainv @ b[:nm].reshape(Mf, 6, k)).reshape(nm, k)
        if nm == n:
            return y.reshape(shape)
        B = Hd[:nm, nm:]
        if self._reduced_is_dense():
            # Stations that all see the same few markers (a handheld walk around one scene) couple
            # every station with every other: S is dense, and sparse products and SuperLU on it
            # cost 10x a dense product and Cholesky (test_13: 11.7 s per step against ~1 s).
            ABd = (Ainv @ B.toarray().reshape(Mf, 6, n - nm)).reshape(nm, n - nm)
            S_d = Hd[nm:, nm:].toarray() - B.T @ ABd
            xc = _dense_spd_solve(S_d, b[nm:] - B.T @ y)
            return np.concatenate([y - ABd @ xc, xc]).reshape(shape)
        Ainv_sp = sp.bsr_matrix((Ainv, np.arange(Mf), np.arange(Mf + 1)), shape=(nm, nm)).tocsr()
        AB = (Ainv_sp @ B).tocsr()
        S = (Hd[nm:, nm:] - B.T @ AB).tocsc()
        xc = splu(S).solve(np.ascontiguousarray(b[nm:] - B.T @ y))
        return np.concatenate([y - AB @ xc, xc.reshape(-1, k)]).reshape(shape)

    def _solve_markers_coupled(self, Hd: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        """``Hd x = b`` through the Schur complement on the markers when relative poses couple
        them (a loose board: its frame and its tags): the markers' block ``A`` of ``Hd`` (block
        diagonal but for the boards' and distances' couplings) factorised as a sparse matrix."""
        from scipy.sparse.linalg import splu

        n, nm = self.n_params, self.n_marker_params
        try:
            lu = splu(Hd[:nm, :nm].tocsc())
        except RuntimeError as e:
            raise RuntimeError("singular markers' block") from e
        if nm == n:
            return lu.solve(b)
        B = Hd[:nm, nm:].toarray()
        AB = lu.solve(B)
        y = lu.solve(b[:nm])
        S = Hd[nm:, nm:].toarray() - B.T @ AB
        xc = _dense_spd_solve(S, b[nm:] - B.T @ y)
        if not np.all(np.isfinite(xc)):
            raise RuntimeError("singular reduced system")
        return np.concatenate([y - AB @ xc, xc])

    def marginal_information(self, H: sp.csr_matrix, cols: np.ndarray) -> np.ndarray:
        """The information of the parameters ``cols`` (sorted) with every other one marginalised:
        the Schur complement of ``H`` (:meth:`normal_equations`' structure) on them, dense. Its
        inverse is their block of ``H^-1`` without forming ``H`` densely (a calibration recording
        of 1,500 stations: 9,000 columns). The stations (:meth:`_station_elimination`) or else the
        markers are eliminated block by block first, so ``cols`` must be cameras' (or markers'
        when the stations are eliminated).

        Raises:
            GeometryError: ``cols`` holds columns of the set eliminated block by block.
        """
        H = H.tocsr()
        if not hasattr(self, "_h_uniq"):
            self._build_normal_pattern()
        if self._station_elimination():
            solve, Bd, C, keep, _ = self._reduce_on_stations(H)
            S = C - Bd.T @ solve(Bd)
        else:
            nm, n = self.n_marker_params, self.n_params
            keep = np.arange(nm, n)
            if nm:
                A = H.data[self._h_marker_blocks]
                B = H[:nm, nm:].toarray()
                AB = (np.linalg.inv(A) @ B.reshape(len(A), 6, n - nm)).reshape(nm, n - nm)
                S = H[nm:, nm:].toarray() - B.T @ AB
            else:
                S = H.toarray()
        cols = np.asarray(cols, dtype=np.int64)
        pos = np.searchsorted(keep, cols)
        if np.any(pos >= len(keep)) or np.any(keep[np.minimum(pos, len(keep) - 1)] != cols):
            raise GeometryError("marginal_information: the columns asked for are eliminated block by block")
        rest = np.setdiff1d(np.arange(len(keep)), pos)
        if len(rest) == 0:
            return S[np.ix_(pos, pos)]
        Srt = S[np.ix_(rest, pos)]
        return S[np.ix_(pos, pos)] - Srt.T @ np.linalg.solve(S[np.ix_(rest, rest)], Srt)

    def _station_elimination(self) -> bool:
        """Whether the steps and the covariances eliminate the stations instead of the markers: when
        there are more stations' unknowns than markers' (a handheld rig walking about one scene:
        1,000 stations, 35 markers), the reduced system over the markers and cameras is a few
        hundred unknowns instead of thousands (dense either way: every station sees the same
        markers). The stations' block is block diagonal, or banded when odometry links stations at
        most ``STATION_ELIMINATION_MAX_BAND`` apart (consecutive ones, in time order)."""
        if not hasattr(self, "_elim_stations"):
            ns = 6 * int(np.sum(self.col_s >= 0))
            nk = self.n_params - ns
            band = 0
            if self.odo is not None:
                band = int(np.max(np.abs(np.asarray(self.odo.station_i) - np.asarray(self.odo.station_j))))
            self._station_band = 6 * band + 5 if band else 0      # half-bandwidth of the stations' block
            self._elim_stations = bool(ns > self.n_marker_params and band <= STATION_ELIMINATION_MAX_BAND
                                       and 0 < nk <= STATION_ELIMINATION_MAX_KEPT and ns * nk <= DENSE_REDUCED_MAX ** 2)
        return self._elim_stations

    def _reduce_on_stations(self, H: sp.csr_matrix, pseudo_inverse: bool = False):
        """The parts of ``H`` (CSR) for the Schur complement on the stations: ``solve(R)`` = the
        stations' block ``A`` of H solved for the (6S, k) right-hand sides ``R`` (its 6x6 blocks
        inverted, or pseudo-inverted; banded Cholesky with odometry: LinAlgError when not positive
        definite), the (6S, K) coupling to the kept unknowns (markers, cameras) dense, the kept
        unknowns' (K, K) block dense, and the kept and eliminated columns."""
        from scipy.linalg import cho_solve_banded, cholesky_banded

        nm, n = self.n_marker_params, self.n_params
        ns = 6 * int(np.sum(self.col_s >= 0))
        elim = np.arange(nm, nm + ns)
        keep = np.r_[np.arange(nm), np.arange(nm + ns, n)]
        Hr = H[nm:nm + ns]
        Ae = Hr[:, nm:nm + ns].tocoo()
        Ae.sum_duplicates()
        u = self._station_band
        if u:
            up = (Ae.row <= Ae.col) & (Ae.col - Ae.row <= u)
            if np.any(np.abs(Ae.col - Ae.row) > u):
                raise GeometryError("bundle adjustment: stations linked farther apart than the band")
            ab = np.zeros((u + 1, ns))
            ab[u + Ae.row[up] - Ae.col[up], Ae.col[up]] = Ae.data[up]
            c = cholesky_banded(ab, check_finite=False)

            def solve(R: np.ndarray) -> np.ndarray:
                return cho_solve_banded((c, False), R, check_finite=False)
        else:
            if np.any(Ae.row // 6 != Ae.col // 6):
                raise GeometryError("bundle adjustment: stations linked to each other cannot be eliminated block "
                                    "by block")
            blocks = np.zeros((ns // 6, 6, 6))
            np.add.at(blocks, (Ae.row // 6, Ae.row % 6, Ae.col % 6), Ae.data)
            Ainv = np.linalg.pinv(blocks, hermitian=True) if pseudo_inverse else np.linalg.inv(blocks)

            def solve(R: np.ndarray) -> np.ndarray:
                return (Ainv @ R.reshape(len(Ainv), 6, -1)).reshape(R.shape)
        return solve, Hr[:, keep].toarray(), H[keep][:, keep].toarray(), keep, elim

    def _reduced_is_dense(self) -> bool:
        """Whether the reduced system ``S`` (stations and cameras) is solved as a dense matrix:
        small enough (``DENSE_REDUCED_MAX`` unknowns, the markers' part of B dense in memory) and at
        least ``DENSE_REDUCED_FILL`` full (its pattern, fixed by the problem, computed once)."""
        if not hasattr(self, "_dense_reduced"):
            if not hasattr(self, "_h_uniq"):
                self._build_normal_pattern()
            n, nm = self.n_params, self.n_marker_params
            nc = n - nm
            dense = False
            if 0 < nc <= DENSE_REDUCED_MAX and nm * nc <= DENSE_REDUCED_MAX ** 2:
                pat = sp.csr_matrix((np.ones(len(self._h_indices)), self._h_indices, self._h_indptr), shape=(n, n))
                Bp = pat[:nm, nm:]
                fill = (pat[nm:, nm:] + Bp.T @ Bp).nnz / float(nc * nc)
                dense = fill >= DENSE_REDUCED_FILL
            self._dense_reduced = dense
        return self._dense_reduced


#: The stations are eliminated (:meth:`_Model._station_elimination`) when at most this many
#: unknowns (markers and cameras) are left ...
STATION_ELIMINATION_MAX_KEPT = 3000
#: ... and odometry links no two stations farther apart than this in the problem's order.
STATION_ELIMINATION_MAX_BAND = 4
#: The reduced system over stations and cameras is solved densely up to this many unknowns ...
DENSE_REDUCED_MAX = 8000
#: ... when at least this fraction of it is non-zero (below, sparse LU).
DENSE_REDUCED_FILL = 0.1


def _dense_spd_solve(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``S x = b`` for a symmetric positive definite ``S`` (Cholesky; LU when rounding makes it
    indefinite). Raises RuntimeError when ``S`` is singular (the caller damps harder)."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve, lu_factor, lu_solve

    try:
        return cho_solve(cho_factor(S, lower=True, check_finite=False), b, check_finite=False)
    except LinAlgError:
        pass
    try:
        lu = lu_factor(S, check_finite=False)
    except (LinAlgError, ValueError) as e:
        raise RuntimeError("singular reduced system") from e
    if not np.all(np.isfinite(lu[0])) or np.min(np.abs(np.diag(lu[0]))) == 0.0:
        raise RuntimeError("singular reduced system")
    return lu_solve(lu, b, check_finite=False)


def _loss_weights(z: np.ndarray, loss: str) -> np.ndarray:
    """IRLS weights rho'(z) of scipy's robust losses at z = (r / f_scale)^2."""
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    if loss == "arctan":
        return 1.0 / (1.0 + z * z)
    return np.ones_like(z)


def _loss_cost(z: np.ndarray, loss: str) -> float:
    """sum rho(z) of scipy's robust losses (the cost is 0.5 f_scale^2 times it)."""
    if loss == "huber":
        return float(np.sum(np.where(z <= 1.0, z, 2.0 * np.sqrt(np.maximum(z, 1.0)) - 1.0)))
    if loss == "soft_l1":
        return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))
    if loss == "cauchy":
        return float(np.sum(np.log1p(z)))
    if loss == "arctan":
        return float(np.sum(np.arctan(z)))
    return float(np.sum(z))


class _LMResult:
    def __init__(self, x, nfev, message, weights):
        self.x, self.nfev, self.message, self.weights = x, nfev, message, weights


def _solve_lm(model: _Model, x0: np.ndarray, f_scale: float, opts: BAOptions, max_nfev: int) -> _LMResult:
    """Levenberg-Marquardt on the sparse normal equations, robust loss by reweighting.

    Each iteration: the normal equations at ``x`` with weights ``rho'((r/f_scale)^2)`` on the
    corner residuals (the priors stay quadratic), assembled from the per-observation blocks
    (:meth:`_Model.normal_equations`), then ``(H + lambda diag(H)) dx = -g`` solved directly
    through the Schur complement on the markers (:meth:`_Model.solve_damped`: LSMR's
    unpreconditioned iterations crawl along the long, weakly constrained directions of a chain of
    stations). A step is kept when the robust cost decreases.
    Stops on ``ftol`` (relative cost decrease), ``xtol`` (step), ``gtol`` (gradient) or ``max_nfev``.
    The result carries the robust weights at the solution (the covariance uses them).
    """
    n_obs = model.n_obs_res
    s2 = f_scale * f_scale

    n_quad = model.n_res - model.n_odo_res        # the priors' rows stay quadratic; odometry: Huber per factor

    def cost_of(r: np.ndarray) -> float:
        return (0.5 * s2 * _loss_cost(r[:n_obs] ** 2 / s2, opts.loss) + 0.5 * float(r[n_obs:n_quad] @ r[n_obs:n_quad])
                + 0.5 * model.odometry_cost(r))

    def weights(r: np.ndarray) -> np.ndarray:
        w = np.ones_like(r)
        w[:n_obs] = _loss_weights(r[:n_obs] ** 2 / s2, opts.loss)
        if model.n_odo_res:
            w[n_quad:] = model.odometry_weights(r)
        return w

    x = x0.copy()
    r = model.residuals(x)
    cost = cost_of(r)
    nfev = 1
    lam = 1e-4
    message = "the maximum number of function evaluations is exceeded"
    while nfev < max_nfev:
        H, g = model.normal_equations(x, r, weights(r))
        if float(np.max(np.abs(g))) <= opts.gtol * max(1.0, cost):
            message = "`gtol` termination condition is satisfied"
            break
        d = np.maximum(H.data[model._h_diag], 1e-12)
        accepted = False
        while nfev < max_nfev:
            try:
                dx = model.solve_damped(H, -g, lam * d)
            except RuntimeError:        # singular: damp harder
                lam *= 10.0
                if lam > 1e10:
                    break
                continue
            x_new = x + dx
            r_new = model.residuals(x_new)
            nfev += 1
            cost_new = cost_of(r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                accepted = True
                break
            lam *= 4.0
            if lam > 1e10:
                break
        if not accepted:
            message = "no step decreases the cost further"
            break
        decrease = cost - cost_new
        small_step = float(np.linalg.norm(dx)) <= opts.xtol * (opts.xtol + float(np.linalg.norm(x_new)))
        x, r, cost = x_new, r_new, cost_new
        lam = max(lam / 3.0, 1e-10)
        if decrease <= opts.ftol * cost:
            message = "`ftol` termination condition is satisfied"
            break
        if small_step:
            message = "`xtol` termination condition is satisfied"
            break
    return _LMResult(x, nfev, message, weights(r))


def _marker_covariances(model: _Model, H: sp.csr_matrix, variance_factor: float
                        ) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """(M, 6, 6) marginal covariances of the markers' (w, t) via the Schur complement of the
    information ``H`` (CSR), and the (6C, 6C) covariance of the cameras' (w, t) when they are
    refined (the cameras' block of the reduced system's inverse: markers and stations
    marginalised), else None."""
    H = H.tocsr()
    nm = model.n_marker_params
    out = np.zeros((model.M, 6, 6))
    cam_cols = np.concatenate([model.col_c[i] + np.arange(6) for i in range(model.C)]) if model.o.refine_extrinsics \
        else None
    solve = None
    if nm and model._station_elimination():
        # The stations eliminated: the inverse of the reduced system over the markers and cameras
        # is exactly their marginal covariance (a few hundred unknowns).
        try:
            solve, Bd, C, keep, elim = model._reduce_on_stations(H, pseudo_inverse=True)
        except np.linalg.LinAlgError:      # the stations' band not positive definite: as below
            solve = None
    if solve is not None:
        Sk = C - Bd.T @ solve(Bd)
        L = _cholesky(Sk)
        if L is not None:
            from scipy.linalg import cho_solve

            Skinv = cho_solve((L, True), np.eye(len(keep)), check_finite=False)
        else:
            Skinv = np.linalg.pinv(Sk, hermitian=True)
        idx = np.flatnonzero(model.col_m >= 0)
        mb = np.arange(len(idx))[:, None] * 6 + np.arange(6)
        out[idx] = variance_factor * Skinv[mb[:, :, None], mb[:, None, :]]
        cam_cov = None
        if cam_cols is not None:
            kc = cam_cols - len(elim)
            cam_cov = variance_factor * Skinv[np.ix_(kc, kc)]
        return 0.5 * (out + np.transpose(out, (0, 2, 1))), cam_cov
    if nm == 0:
        if cam_cols is None:
            return out, None
        Hinv = np.linalg.pinv(H.toarray(), hermitian=True)
        return out, variance_factor * Hinv[np.ix_(cam_cols, cam_cols)]
    if model._rel_coupled:
        return _coupled_marker_covariances(model, H, variance_factor, cam_cols)
    # A is block diagonal (6x6 per free marker, in column order): gather and invert the blocks.
    idx = np.flatnonzero(model.col_m >= 0)
    Mf = len(idx)
    Am = H[:nm, :nm].tocoo()
    blocks = np.zeros((Mf, 6, 6))
    np.add.at(blocks, (Am.row // 6, Am.row % 6, Am.col % 6), Am.data)
    Ainv = np.linalg.pinv(blocks, hermitian=True)
    cov = Ainv.copy()
    cam_cov = None
    if model.n_params > nm:
        Ainv_sp = sp.bsr_matrix((Ainv, np.arange(Mf), np.arange(Mf + 1)), shape=(nm, nm)).tocsr()
        B = H[:nm, nm:].tocsr()
        K = (Ainv_sp @ B).tocsr()                                    # A^-1 B, (nm, nc) sparse
        nc = model.n_params - nm
        if model._reduced_is_dense():
            Sred = H[nm:, nm:].toarray() - B.T @ K.toarray()
        else:
            Sred = H[nm:, nm:].toarray() - (B.T @ K).toarray()
        L = _cholesky(Sred)
        if L is not None and nm <= nc:
            # S = L L^T (the gauge is fixed: positive definite): K_i S^-1 K_i^T = X_i^T X_i with
            # X = L^-1 K^T, a triangular solve per chunk of markers (nc^2 per marker) instead of
            # S's pseudo-inverse (an eigendecomposition, ~10 nc^3: 60 % of test_13's build-map).
            from scipy.linalg import solve_triangular

            chunk = 256
            for m0 in range(0, Mf, chunk):
                m1 = min(m0 + chunk, Mf)
                X = solve_triangular(L, K[6 * m0:6 * m1].toarray().T, lower=True, check_finite=False)
                Xb = X.T.reshape(m1 - m0, 6, nc)
                cov[m0:m1] += Xb @ np.transpose(Xb, (0, 2, 1))
            if cam_cols is not None:
                E = np.zeros((nc, len(cam_cols)))
                E[cam_cols - nm, np.arange(len(cam_cols))] = 1.0
                Y = solve_triangular(L, E, lower=True, check_finite=False)
                cam_cov = variance_factor * (Y.T @ Y)
            out[idx] = cov * variance_factor
            return 0.5 * (out + np.transpose(out, (0, 2, 1))), cam_cov
        if L is not None:
            from scipy.linalg import cho_solve

            Sinv = cho_solve((L, True), np.eye(nc), check_finite=False)
        else:
            Sinv = np.linalg.pinv(Sred, hermitian=True)
        # cov_i = A_i^-1 + K_i S^-1 K_i^T, K_i the marker's 6 rows of K (a few stations + the
        # cameras): G = K S^-1 in chunks of markers, then only K's non-zeros are visited.
        Kc = K.tocoo()
        order = np.argsort(Kc.row, kind="stable")
        kr, kc, kv = Kc.row[order], Kc.col[order], Kc.data[order]
        chunk = 256
        bounds = np.searchsorted(kr, np.arange(0, Mf + chunk, chunk) * 6)
        for j in range(len(bounds) - 1):
            lo, hi = bounds[j], bounds[j + 1]
            if lo == hi:
                continue
            m0 = j * chunk
            G = np.asarray(K[6 * m0:6 * min(m0 + chunk, Mf)] @ Sinv)  # (6 * chunk, nc)
            r, c, v = kr[lo:hi], kc[lo:hi], kv[lo:hi]
            blk = r // 6
            rows = 6 * (blk - m0)[:, None] + np.arange(6)             # the block's 6 rows of G
            contrib = G[rows, c[:, None]] * v[:, None]                 # (nnz, 6): [a] for column b = r % 6
            lin = (36 * np.repeat(blk, 6) + 6 * np.tile(np.arange(6), len(blk)) + np.repeat(r % 6, 6))
            cov += np.bincount(lin, weights=contrib.ravel(), minlength=36 * Mf).reshape(Mf, 6, 6)
        if cam_cols is not None:
            cam_cov = variance_factor * Sinv[np.ix_(cam_cols - nm, cam_cols - nm)]
    out[idx] = cov * variance_factor
    return 0.5 * (out + np.transpose(out, (0, 2, 1))), cam_cov


def _coupled_marker_covariances(model: _Model, H: sp.csr_matrix, variance_factor: float,
                                cam_cols: Optional[np.ndarray]) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """:func:`_marker_covariances` when relative poses couple the markers (loose boards), exactly:
    the markers' block ``A`` of ``H`` factorised as a sparse matrix, ``cov_i = (A^-1)_ii + K_i S^-1
    K_i^T`` with ``K = A^-1 B`` and ``S = C - B^T K`` (the columns of ``A^-1`` by chunks of markers)."""
    from scipy.sparse.linalg import splu

    nm, n = model.n_marker_params, model.n_params
    idx = np.flatnonzero(model.col_m >= 0)
    Mf = len(idx)
    out = np.zeros((model.M, 6, 6))
    A = H[:nm, :nm].tocsc()
    try:
        lu = splu(A)
        solve = lu.solve
    except RuntimeError:
        Ainv = np.linalg.pinv(A.toarray(), hermitian=True)

        def solve(R: np.ndarray) -> np.ndarray:
            return Ainv @ R
    cov = np.zeros((Mf, 6, 6))
    chunk = 128
    for m0 in range(0, Mf, chunk):
        m1 = min(m0 + chunk, Mf)
        E = np.zeros((nm, 6 * (m1 - m0)))
        E[6 * m0 + np.arange(6 * (m1 - m0)), np.arange(6 * (m1 - m0))] = 1.0
        X = solve(E)[6 * m0:6 * m1].reshape(m1 - m0, 6, m1 - m0, 6)
        cov[m0:m1] = X[np.arange(m1 - m0), :, np.arange(m1 - m0), :]
    cam_cov = None
    if n > nm:
        B = H[:nm, nm:].toarray()
        K = solve(B)
        Sred = H[nm:, nm:].toarray() - B.T @ K
        Sinv = np.linalg.pinv(Sred, hermitian=True)
        Kb = K.reshape(Mf, 6, n - nm)
        cov += Kb @ Sinv @ np.transpose(Kb, (0, 2, 1))
        if cam_cols is not None:
            cam_cov = variance_factor * Sinv[np.ix_(cam_cols - nm, cam_cols - nm)]
    out[idx] = cov * variance_factor
    return 0.5 * (out + np.transpose(out, (0, 2, 1))), cam_cov


def _cholesky(S: np.ndarray) -> Optional[np.ndarray]:
    """Lower Cholesky factor of a symmetric ``S``, or None when it is not positive definite."""
    from scipy.linalg import LinAlgError, cholesky

    try:
        return cholesky(S, lower=True, check_finite=False)
    except LinAlgError:
        return None


def bundle_adjust(prob: BAProblem, opts: Optional[BAOptions] = None) -> BAResult:
    """Refine the map by minimising the corner reprojection errors (see the module docstring).

    Runs with one BLAS thread (threadpoolctl): on a busy 2-core machine OpenBLAS's worker threads
    spin against each other and the other processes; a 28-marker adjustment took 129 s with them
    and 8.6 s without (the dense SVDs of scipy's trust region).

    Raises:
        GeometryError: no observations, or no gauge.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _bundle_adjust(prob, opts)


def _bundle_adjust(prob: BAProblem, opts: Optional[BAOptions] = None) -> BAResult:
    opts = opts or BAOptions()
    t0 = time.perf_counter()
    c0 = time.process_time()
    model = _Model(prob, opts)
    x0 = np.zeros(model.n_params)
    if prob.T_base_cams_start is not None and opts.refine_extrinsics:
        for i in range(model.C):
            T = np.asarray(prob.T_base_cams_start[i])
            c = model.col_c[i]
            x0[c:c + 3] = Rotation.from_matrix(T[:3, :3] @ model.R_c0[i].T).as_rotvec()
            x0[c + 3:c + 6] = T[:3, 3] - model.t_c0[i]
    r0 = model.residuals(x0)[: model.n_obs_res] * opts.pixel_noise
    rms0 = float(np.sqrt(np.mean(r0 ** 2)))
    if model.n_params == 0:
        res_x, nfev, status, J = x0, 0, "nothing to refine", None
    else:
        # Small problems: the exact (dense) trust-region subproblem converges in far fewer
        # iterations; large ones keep the Jacobian sparse and use LSMR.
        tr_solver = "exact" if model.n_params <= opts.dense_max_params else "lsmr"
        jac = model.jacobian if tr_solver == "lsmr" else (lambda x: model.jacobian(x).toarray())

        def solve(x_start: np.ndarray, f_scale: float, max_nfev: int):
            if opts.solver == "lm":
                return _solve_lm(model, x_start, f_scale, opts, max_nfev)
            return least_squares(model.residuals, x_start, jac=jac, method="trf", loss=opts.loss,
                                 f_scale=f_scale, x_scale="jac", tr_solver=tr_solver,
                                 tr_options={"atol": opts.lsmr_tol, "btol": opts.lsmr_tol} if tr_solver == "lsmr" else {},
                                 ftol=opts.ftol, xtol=opts.xtol, gtol=opts.gtol, max_nfev=max_nfev)

        # Far from the solution (an initialisation off by several pixels everywhere, e.g. a long
        # chain of stations), nearly every residual sits in the loss's robust (linear) branch and
        # scipy's trust region crawls: a 5.7 px start stayed at 5.7 px. A first pass with the
        # robust scale widened to the bulk of the initial residuals (3 x their robust spread)
        # converges like plain least squares while still down-weighting gross outliers; the
        # second pass uses the nominal scale.
        nfev = 0
        x_start = x0
        spread = 1.4826 * float(np.median(np.abs(model.residuals(x0)[: model.n_obs_res])))
        if opts.loss != "linear" and 3.0 * spread > 2.0 * opts.robust_scale:
            first = solve(x0, 3.0 * spread, opts.max_nfev)
            x_start, nfev = first.x, int(first.nfev)
        res = solve(x_start, opts.robust_scale, max(opts.max_nfev - nfev, 10))
        res_x, nfev, status = res.x, nfev + int(res.nfev), str(res.message)
        J = res.weights if opts.solver == "lm" else res.jac
    r = model.residuals(res_x)
    r_obs = r[: model.n_obs_res] * opts.pixel_noise
    per_obs = np.sqrt(np.mean(r_obs.reshape(model.N, 8) ** 2, axis=1))
    rms1 = float(np.sqrt(np.mean(r_obs ** 2)))
    # Variance factor from the inliers (beyond robust_scale sigmas the loss down-weights anyway).
    inl = np.abs(r) <= opts.robust_scale
    vf = float(np.sum(r[inl] ** 2) / max(int(inl.sum()) - model.n_params, 1)) if np.any(inl) else 1.0
    (wm, Rm, tm), (ws, Rs, ts, _), (wc, Rc, tc, _) = model.poses(res_x)
    T_m = np.tile(np.eye(4), (model.M, 1, 1))
    T_m[:, :3, :3], T_m[:, :3, 3] = Rm, tm
    T_s = np.tile(np.eye(4), (model.S, 1, 1))
    T_s[:, :3, :3], T_s[:, :3, 3] = Rs, ts
    T_c = np.tile(np.eye(4), (model.C, 1, 1))
    T_c[:, :3, :3], T_c[:, :3, 3] = Rc, tc
    cov = cam_cov = None
    if opts.covariance and J is not None:
        # The priors' sigmas are absolute: only the corner rows carry the variance factor (else
        # what only the priors determine -- a turn of the whole ring against the robot -- would
        # shrink with a small pixel noise).
        priors = model.n_res > model.n_obs_res
        rows = np.ones(model.n_res)
        if priors:
            rows[: model.n_obs_res] = 1.0 / max(vf, 1e-12)
        if isinstance(J, np.ndarray) and J.ndim == 1:       # solver lm: the robust weights at the solution
            H = model.normal_equations(res_x, r, J * rows)[0]
            if model._dist_coupled and not model._rel_coupled and not model._station_elimination():
                # The markers' covariances are computed block by block: without the distances
                # that couple markers (less information: the covariances are conservative).
                H = model.without_distances(H, model._dist_E)
        else:                                               # solver trf: scipy's (loss-scaled) Jacobian
            Jm = J if sp.issparse(J) else sp.csr_matrix(J)
            Jm = (sp.diags(np.sqrt(rows)) @ Jm).tocsr()
            if model._dist_coupled and not model._rel_coupled and not model._station_elimination():
                keep = np.setdiff1d(np.arange(model.n_res), model._dist_rows)
                Jm = Jm[keep]
            H = (Jm.T @ Jm).tocsr()
        cov, cam_cov = _marker_covariances(model, H, 1.0 if priors else vf)
    seconds = time.perf_counter() - t0
    cpu = time.process_time() - c0
    logger.info("bundle adjustment: %d markers, %d stations, %d observations, %d params: RMS %.3f -> %.3f px "
                "in %.2f s (%.2f s CPU; %d evaluations; %s)", model.M, model.S, model.N, model.n_params, rms0, rms1,
                seconds, cpu, nfev, status)
    return BAResult(T_W_markers=T_m, T_W_stations=T_s, T_base_cams=T_c, marker_cov=cov, rms_px_before=rms0,
                    rms_px_after=rms1, per_obs_rms_px=per_obs, variance_factor=vf, seconds=seconds, nfev=nfev,
                    status=status, n_residuals=model.n_res, n_params=model.n_params, camera_cov=cam_cov,
                    cpu_seconds=cpu)


def observation_rms_px(prob: BAProblem) -> np.ndarray:
    """(N,) RMS corner reprojection error (px, undistorted) of every observation at the problem's poses.

    What a map that is not adjusted (method ``paper``) reports as its reprojection error.
    """
    model = _Model(prob, BAOptions(pixel_noise=1.0))
    r = model.residuals(np.zeros(model.n_params))[: model.n_obs_res]
    return np.sqrt(np.mean(r.reshape(model.N, 8) ** 2, axis=1))


def marker_std_in_frame(cov6: np.ndarray, T_W_marker: np.ndarray, T_W_frame: np.ndarray):
    """(position std (3,) along the axes of ``frame``, rotation std (3,) about the marker's axes).

    ``cov6`` is the (w, t) covariance in W (w: left rotation perturbation, t: translation).
    """
    R_fW = T_W_frame[:3, :3].T
    Ct = R_fW @ cov6[3:, 3:] @ R_fW.T
    R_mW = T_W_marker[:3, :3].T
    Cr = R_mW @ cov6[:3, :3] @ R_mW.T
    return np.sqrt(np.clip(np.diag(Ct), 0.0, None)), np.sqrt(np.clip(np.diag(Cr), 0.0, None))


def camera_cov_in_optical_frames(camera_cov: np.ndarray, T_base_cams: np.ndarray) -> np.ndarray:
    """:attr:`BAResult.camera_cov` in the convention of the ring file's ``extrinsics_std``.

    The adjustment moves camera c by ``R = exp(w) R_c``, ``t = t_c + dt`` (base frame); the same
    motion in the camera's own optical frame is ``T_base_cam · D`` with ``D = (exp(R_c^T w),
    R_c^T dt)``, so each 6x6 block (c, d) becomes ``B_c C_cd B_d^T`` with ``B_c = diag(R_c^T, R_c^T)``.
    """
    C = len(T_base_cams)
    B = np.zeros((6 * C, 6 * C))
    for k in range(C):
        Rt = np.asarray(T_base_cams[k])[:3, :3].T
        B[6 * k:6 * k + 3, 6 * k:6 * k + 3] = Rt
        B[6 * k + 3:6 * k + 6, 6 * k + 3:6 * k + 6] = Rt
    out = B @ camera_cov @ B.T
    return 0.5 * (out + out.T)
