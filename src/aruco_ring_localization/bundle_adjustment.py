"""Bundle adjustment of a marker map: marker poses, robot (station) poses and optionally the ring.

Unknowns (all in one frame W, the robot's base frame at the reference station):

* ``T_W_marker`` for every marker but the fixed one (the gauge: the reference marker),
* ``T_W_base`` for every station (a robot placement; many frames may share one),
* optionally ``T_base_cam`` of every camera, with a Gaussian prior around the calibration.

Measurements: every detected corner of every observation. A corner ``X`` (marker frame) is seen by
camera ``c`` of station ``s`` at ``p_c = T_base_cam^-1 · T_W_base^-1 · T_W_marker · X``, and the
residual is ``f · (p_c.xy / p_c.z - xy_obs) / pixel_noise`` where ``xy_obs`` are the observed
corners undistorted to normalised coordinates (``CameraModel.normalize``) and ``f`` the focal
length in pixels: the pixel reprojection error of an ideal pinhole camera, in units of the
expected corner noise. Undistorting once keeps the lens model out of the solver; near the
image centre it equals the raw pixel error, at the border it differs by the local lens scale.

Each pose is a perturbation of its initial value, ``R = exp(w) R0``, ``t = t0 + dt`` (w in the
parent frame), so the parameters stay near zero. The Jacobian is analytic (left Jacobian of
SO(3) included) and sparse; the solver is :func:`scipy.optimize.least_squares` (``trf``, ``lsmr``
on the sparse Jacobian, ``x_scale='jac'``, a robust loss).

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
from .config import in_radians, param
from .errors import GeometryError
from .markers import marker_corners

logger = logging.getLogger(__name__)


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
                                       "(tr_solver exact), above with LSMR on the sparse Jacobian")
    ftol: float = param(1e-8, "solver tolerance on the cost")
    xtol: float = param(1e-10, "solver tolerance on the step")
    gtol: float = param(1e-10, "solver tolerance on the gradient")
    lsmr_tol: float = param(1e-10, "LSMR's atol/btol for the sparse trust-region steps (looser is faster per "
                                   "iteration, enough for quick adjustments of an initialisation)")
    covariance: bool = param(True, "compute per-marker covariances")

    extrinsics_rot_sigma = in_radians("extrinsics_rot_sigma_deg")


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
        if prob.fixed_marker is None and prob.fixed_station is None and not opts.refine_extrinsics:
            raise GeometryError("bundle adjustment needs a gauge: a fixed marker or a fixed station")
        self.M, self.S, self.C, self.N = M, S, C, N
        # Column offset of each pose block; -1 for fixed ones.
        self.col_m = np.full(M, -1)
        self.col_s = np.full(S, -1)
        self.col_c = np.full(C, -1)
        col = 0
        for i in range(M):
            if i != prob.fixed_marker:
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
        unit = marker_corners(1.0)
        self.X = unit[None, :, :] * np.asarray(prob.sizes, dtype=float)[prob.obs_marker][:, None, None]
        self.scale = prob.obs_focal / opts.pixel_noise            # (N, 2)
        self.n_obs_res = 8 * N
        self.n_prior_res = 6 * C if opts.refine_extrinsics else 0
        self.n_res = self.n_obs_res + self.n_prior_res
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
        self.rows = np.concatenate(self._blk_rows + ([self._prior_rows] if self.n_prior_res else []))
        self.cols = np.concatenate(self._blk_cols + ([self._prior_cols] if self.n_prior_res else []))

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
        a = np.einsum("nij,nkj->nki", Rm[im], self.X)                # R_m X, (N, 4, 3)
        pW = a + tm[im][:, None, :]
        q = pW - ts[is_][:, None, :]                                  # p_W - t_s
        pb = np.einsum("nji,nkj->nki", Rs[is_], q)                    # R_s^T q
        q2 = pb - tc[ic][:, None, :]
        pc = np.einsum("nji,nkj->nki", Rc[ic], q2)                    # R_c^T q2
        return (wm, Rm, tm), (ws, Rs, ts, Es), (wc, Rc, tc, Ec), a, q, q2, pc

    def residuals(self, x: np.ndarray) -> np.ndarray:
        *_, pc = self._forward(x)
        z = pc[..., 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        proj = pc[..., :2] / z[..., None]
        r = (proj - self.p.obs_xy) * self.scale[:, None, :]
        out = r.ravel()
        if self.n_prior_res:
            prior = x[self._prior_cols].reshape(self.C, 6).copy()
            prior[:, :3] /= self.o.extrinsics_rot_sigma
            prior[:, 3:] /= self.o.extrinsics_trans_sigma
            out = np.concatenate([out, prior.ravel()])
        return out

    def jacobian(self, x: np.ndarray) -> sp.csr_matrix:
        (wm, Rm, tm), (ws, Rs, ts, Es), (wc, Rc, tc, Ec), a, q, q2, pc = self._forward(x)
        im, is_, ic = self.p.obs_marker, self.p.obs_station, self.p.obs_camera
        z = pc[..., 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        # d(scaled projection)/d p_c: (N, 4, 2, 3)
        D = np.zeros(pc.shape[:2] + (2, 3))
        D[..., 0, 0] = 1.0 / z
        D[..., 1, 1] = 1.0 / z
        D[..., 0, 2] = -pc[..., 0] / z ** 2
        D[..., 1, 2] = -pc[..., 1] / z ** 2
        D *= self.scale[:, None, :, None]
        RcT = np.transpose(Rc[ic], (0, 2, 1))                         # (N, 3, 3)
        RsT = np.transpose(Rs[is_], (0, 2, 1))
        DRc = np.einsum("nkij,njl->nkil", D, RcT)                     # d r / d p_b, (N, 4, 2, 3)
        DRcRs = np.einsum("nkij,njl->nkil", DRc, RsT)                 # d r / d p_W
        data = []
        # Marker: dp_W/dw = -[R_m X]x J_l(w_m), dp_W/dt = I.
        Jl_m = geo.so3_left_jacobian(wm)[im]                         # (N, 3, 3)
        dpw_dw = -np.einsum("nkij,njl->nkil", geo.skew(a), Jl_m)     # (N, 4, 3, 3)
        jm = np.concatenate([np.einsum("nkij,nkjl->nkil", DRcRs, dpw_dw), DRcRs], axis=-1)
        data.append(jm[self._blk_masks[0]])
        # Station: dp_b/dv = R_s0^T [exp(-v) q]x J_l(-v), dp_b/dt_s = -R_s^T.
        Einv = np.transpose(Es, (0, 2, 1))[is_]                        # exp(-v)
        Jl_s = geo.so3_left_jacobian(-ws)[is_]
        u = np.einsum("nij,nkj->nki", Einv, q)
        R0T = np.transpose(self.R_s0[is_], (0, 2, 1))
        dpb_dv = np.einsum("nij,nkjl->nkil", R0T, np.einsum("nkij,njl->nkil", geo.skew(u), Jl_s))
        js = np.concatenate([np.einsum("nkij,nkjl->nkil", DRc, dpb_dv), -DRcRs], axis=-1)
        data.append(js[self._blk_masks[1]])
        if self.o.refine_extrinsics:
            Einv_c = np.transpose(Ec, (0, 2, 1))[ic]
            Jl_c = geo.so3_left_jacobian(-wc)[ic]
            u2 = np.einsum("nij,nkj->nki", Einv_c, q2)
            Rc0T = np.transpose(self.R_c0[ic], (0, 2, 1))
            dpc_de = np.einsum("nij,nkjl->nkil", Rc0T, np.einsum("nkij,njl->nkil", geo.skew(u2), Jl_c))
            jc = np.concatenate([np.einsum("nkij,nkjl->nkil", D, dpc_de), -DRc], axis=-1)
            data.append(jc[self._blk_masks[2]])
        if self.n_prior_res:
            pd = np.tile(np.r_[np.full(3, 1.0 / self.o.extrinsics_rot_sigma),
                               np.full(3, 1.0 / self.o.extrinsics_trans_sigma)], self.C)
            data.append(pd)
        return sp.csr_matrix((np.concatenate(data), (self.rows, self.cols)), shape=(self.n_res, self.n_params))


def _marker_covariances(model: _Model, J: sp.csr_matrix, variance_factor: float
                        ) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """(M, 6, 6) marginal covariances of the markers' (w, t) via the Schur complement, and the
    (6C, 6C) covariance of the cameras' (w, t) when they are refined (the cameras' block of the
    reduced system's inverse: markers and stations marginalised), else None."""
    H = (J.T @ J).tocsr()
    nm = model.n_marker_params
    out = np.zeros((model.M, 6, 6))
    cam_cols = np.concatenate([model.col_c[i] + np.arange(6) for i in range(model.C)]) if model.o.refine_extrinsics \
        else None
    if nm == 0:
        if cam_cols is None:
            return out, None
        Hinv = np.linalg.pinv(H.toarray(), hermitian=True)
        return out, variance_factor * Hinv[np.ix_(cam_cols, cam_cols)]
    # A is block diagonal (6x6 per free marker): invert block by block.
    Ainv_blocks = []
    idx = [i for i in range(model.M) if model.col_m[i] >= 0]
    Hm = H[:nm, :nm].tocsr()
    for i in idx:
        c = model.col_m[i]
        blk = Hm[c:c + 6, c:c + 6].toarray()
        Ainv_blocks.append(np.linalg.pinv(blk))
    Ainv = sp.block_diag(Ainv_blocks, format="csr")
    if model.n_params > nm:
        B = H[:nm, nm:].tocsr()
        Cm = H[nm:, nm:].toarray()
        K = (Ainv @ B).tocsr()                                       # A^-1 B, (nm, nc) sparse
        Sred = Cm - (B.T @ K).toarray()
        Sinv = np.linalg.pinv(Sred, hermitian=True)
        G = K @ Sinv                                                 # dense (nm, nc)
        Kd = K.tocsr()
        for k, i in enumerate(idx):
            c = model.col_m[i]
            Ki = Kd[c:c + 6].toarray()
            out[i] = Ainv_blocks[k] + G[c:c + 6] @ Ki.T
        cam_cov = None if cam_cols is None else variance_factor * Sinv[np.ix_(cam_cols - nm, cam_cols - nm)]
    else:
        for k, i in enumerate(idx):
            out[i] = Ainv_blocks[k]
        cam_cov = None
    out *= variance_factor
    return 0.5 * (out + np.transpose(out, (0, 2, 1))), cam_cov


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
        res_x, nfev, status, J = res.x, nfev + int(res.nfev), str(res.message), res.jac
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
        Jm = J if sp.issparse(J) else sp.csr_matrix(J)
        if model.n_prior_res:
            # The priors' sigmas are absolute: only the corner rows carry the variance factor (else
            # what only the priors determine -- a turn of the whole ring against the robot -- would
            # shrink with a small pixel noise).
            rows = np.ones(model.n_res)
            rows[: model.n_obs_res] = 1.0 / np.sqrt(max(vf, 1e-12))
            cov, cam_cov = _marker_covariances(model, (sp.diags(rows) @ Jm).tocsr(), 1.0)
        else:
            cov, cam_cov = _marker_covariances(model, Jm.tocsr(), vf)
    seconds = time.perf_counter() - t0
    logger.info("bundle adjustment: %d markers, %d stations, %d observations, %d params: RMS %.3f -> %.3f px "
                "in %.2f s (%d evaluations; %s)", model.M, model.S, model.N, model.n_params, rms0, rms1,
                seconds, nfev, status)
    return BAResult(T_W_markers=T_m, T_W_stations=T_s, T_base_cams=T_c, marker_cov=cov, rms_px_before=rms0,
                    rms_px_after=rms1, per_obs_rms_px=per_obs, variance_factor=vf, seconds=seconds, nfev=nfev,
                    status=status, n_residuals=model.n_res, n_params=model.n_params, camera_cov=cam_cov)


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
