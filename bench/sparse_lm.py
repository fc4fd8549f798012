"""One sparse Levenberg-Marquardt loop for the real-data diagnostics (bench/real_objective.py,
bench/real_board_model.py), which re-enact TagSLAM's stated problems by plain least squares.

Not the package's bundle adjustment (src/aruco_ring_localization/bundle_adjustment.py): these
diagnostics need the plain sum of squares with nothing robust and nothing held back, over a chosen
set of free columns.
"""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray],
                        jacobian: Callable[[np.ndarray, np.ndarray], sp.spmatrix],
                        x0: np.ndarray, free: Optional[np.ndarray] = None, iterations: int = 30,
                        damping: float = 1e-4, rel_tol: float = 1e-7,
                        floor: float = 1e-12) -> Tuple[np.ndarray, float, int]:
    """Minimise ``0.5 |residuals(x)|^2`` over the columns ``free`` of ``x`` (all when None).

    ``jacobian(x, r)`` gives the sparse Jacobian over the free columns only. Marquardt's scaling
    (``damping`` times the normal matrix's diagonal, a column with an empty diagonal floored at
    ``floor`` times its largest entry); the damping falls by 3 after an accepted step and grows by
    4 after a refused one. Stops when a step gains less than ``rel_tol`` of the cost, when no step
    is accepted below a damping of 1e8, or after ``iterations``: (x, cost, iterations used).
    """
    x = np.array(x0, dtype=float)
    r = residuals(x)
    cost, lam = 0.5 * float(r @ r), damping
    for it in range(1, iterations + 1):
        J = jacobian(x, r)
        H = (J.T @ J).tocsc()
        g = J.T @ r
        d = H.diagonal()
        d_floor = floor * float(d.max()) * (d <= 0)
        done = False
        while True:
            step = spla.spsolve(H + sp.diags(lam * d + d_floor), -g)
            x2 = x.copy()
            if free is None:
                x2 += step
            else:
                x2[free] += step
            r2 = residuals(x2)
            c2 = 0.5 * float(r2 @ r2)
            if c2 < cost:
                done = cost - c2 < rel_tol * cost
                x, r, cost, lam = x2, r2, c2, max(lam / 3.0, 1e-9)
                break
            lam *= 4.0
            if lam > 1e8:
                done = True
                break
        if done:
            return x, cost, it
    return x, cost, iterations
