"""Standard errors and 95 % intervals of the free parameters from a covariance of the
scaled decision variables (:meth:`identify.fitting.covariance.Covariance.covariance`),
in natural units.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Z95", "covariance_and_scale", "standard_errors"]

Z95 = 1.959963984540054


def _scaled_ci(theta, sigma, tm, i):
    """The 95 % interval θ ± Z95·σ of scaled parameter i, in natural units."""
    lo, hi = theta - Z95 * sigma, theta + Z95 * sigma
    if tm.log[i]:
        return (float(tm.scale[i] * math.exp(lo)), float(tm.scale[i] * math.exp(hi)))
    return (float(tm.scale[i] * lo), float(tm.scale[i] * hi))


def covariance_and_scale(prob, w, mode: str, redchi: float):
    """(covariance of the scaled parameters, the factor it is used with): the sandwich
    carries its own scale; the model-based one is scaled by χ²_red (scale_covariance)."""
    C = prob.covariance(w, robust=mode)
    scale = (redchi if prob.opts.scale_covariance else 1.0) if mode == "model" else 1.0
    return C, scale


def standard_errors(tm, th, C, scale) -> list:
    """Per parameter (stderr in natural units or None, σ on the fit scale, 95 % interval)."""
    d = tm.jacobian_diag(th)
    out = []
    for i in range(len(tm.names)):
        var = C[i, i] * scale if np.isfinite(C[i, i]) else np.nan
        sig_th = math.sqrt(var) if var >= 0 and np.isfinite(var) else float("nan")
        se = abs(d[i]) * sig_th if np.isfinite(sig_th) else None
        try:
            ci = _scaled_ci(th[i], sig_th, tm, i) if se is not None else None
        except OverflowError:  # a log-scaled parameter the data do not determine at all
            ci = None
        out.append((se, sig_th, ci))
    return out

