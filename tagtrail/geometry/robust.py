"""Robust M-estimator losses ``rho(s)`` of a squared, scale-normalised residual norm ``s``.

Same conventions as ``scipy.optimize.least_squares``: ``rho(s) ~ s`` for small ``s``; the cost of a
residual block ``r`` with scale ``f`` is ``f^2 rho(|r|^2 / f^2)`` and its IRLS weight is
``rho'(|r|^2 / f^2)`` (Triggs et al. 2000; Zhang 1997).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from tagtrail.geometry.arrays import F64

LossName = Literal["linear", "soft_l1", "huber", "cauchy"]


def rho(name: LossName, s: ArrayLike) -> tuple[F64, F64]:
    """``(rho(s), rho'(s))`` elementwise for ``s >= 0``."""
    s = np.asarray(s, dtype=np.float64)
    if name == "linear":
        return s.copy(), np.ones_like(s)
    if name == "soft_l1":
        r = np.sqrt(1.0 + s)
        return 2.0 * (r - 1.0), 1.0 / r
    if name == "huber":
        big = s > 1.0
        ss = np.where(big, s, 1.0)
        return np.where(big, 2.0 * np.sqrt(ss) - 1.0, s), np.where(big, 1.0 / np.sqrt(ss), 1.0)
    if name == "cauchy":
        return np.log1p(s), 1.0 / (1.0 + s)
    raise ValueError(f"unknown loss {name!r} (expected linear, soft_l1, huber or cauchy)")


def irls_weights(name: LossName, sq_norm: ArrayLike, f_scale: float) -> F64:
    """IRLS weights ``rho'(|r|^2 / f^2)`` of residual blocks with squared norms ``sq_norm``."""
    return rho(name, np.asarray(sq_norm, dtype=np.float64) / (f_scale * f_scale))[1]
