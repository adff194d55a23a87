"""Rate-and-state friction as friction labs write it, driven through a spring by a load
point that moves continuously (velocity steps, slide-hold-slide).

    μ = μ0 + a·ln(V/V0) + b·ln(V0·θ/Dc)
    dμ/dt = k·(V_lp(t) − V)                          (quasi-static spring, k in 1/µm)
    aging (Dieterich):  dθ/dt = 1 − V·θ/Dc
    slip  (Ruina):      dθ/dt = −(V·θ/Dc)·ln(V·θ/Dc)

V0 is the reference velocity at which μ0 is stated (the velocity before the first step,
as labs report it). The integration runs in lab units (µm, s) on the state
(μ, Ω = ln(V0·θ/Dc)): Ω is 0 at steady sliding at V0 and stays of order one, where θ
spans decades; V = V0·exp((μ − μ0 − b·Ω)/a).

The same equations as the toolkit's logarithmic law in the limit V, V0 ≫ vc; kept apart
because labs state μ0 at a reference velocity and have no cut-off velocity.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import casadi as ca
import numpy as np

__all__ = ["RSF_LAWS", "RSF_PARAMETERS", "VelocityDrive", "rsf_rhs", "simulate_rsf", "transient_function"]

RSF_LAWS = ("aging", "slip")
RSF_PARAMETERS = ("mu0", "a", "b", "Dc", "k")
"""Names and lab units: μ0 (-), a (-), b (-), Dc (µm), k (1/µm: friction per µm of
load-point displacement)."""


@dataclass(frozen=True)
class VelocityDrive:
    """A load point that moves at ``velocities_um_per_s[i]`` from ``times_s[i]`` on (the
    first entry is the velocity before anything else, at ``times_s[0]``)."""

    times_s: tuple[float, ...]
    velocities_um_per_s: tuple[float, ...]

    def __post_init__(self):
        t, v = np.asarray(self.times_s, float), np.asarray(self.velocities_um_per_s, float)
        if t.ndim != 1 or t.size == 0 or t.size != v.size:
            raise ValueError("a velocity drive needs as many times_s as velocities_um_per_s (at least one)")
        if np.any(np.diff(t) <= 0):
            raise ValueError(f"a velocity drive's times_s must increase: {list(t)}")
        if np.any(v < 0) or not np.all(np.isfinite(v)):
            raise ValueError(f"a velocity drive's velocities_um_per_s must be finite and >= 0: {list(v)}")

    def velocity_at(self, t: np.ndarray) -> np.ndarray:
        """The load-point velocity in force during each time ``t`` (µm/s)."""
        idx = np.searchsorted(np.asarray(self.times_s), np.asarray(t, float), side="right") - 1
        return np.asarray(self.velocities_um_per_s, float)[np.clip(idx, 0, None)]

    def displacement_um(self, t: np.ndarray) -> np.ndarray:
        """The load point's displacement (µm) at the times ``t`` from its position at
        ``times_s[0]``."""
        t = np.asarray(t, float)
        times = np.asarray(self.times_s, float)
        vels = np.asarray(self.velocities_um_per_s, float)
        edges = np.concatenate([times, [max(float(t.max(initial=times[-1])), times[-1])]])
        x = np.zeros_like(t)
        for i, v in enumerate(vels):  # (over the stretches, not the samples)
            x += v * np.clip(np.minimum(t, edges[i + 1]) - edges[i], 0, None)
        return x

    def to_dict(self) -> dict:
        return dict(kind="velocity_steps", times_s=list(map(float, self.times_s)),
                    velocities_um_per_s=list(map(float, self.velocities_um_per_s)))


def rsf_rhs(law: str, mu, omega, v_lp, p: Mapping, ops=ca):
    """(dμ/dt, dΩ/dt) of the law ``law`` ('aging' or 'slip') at the state (μ, Ω), the
    load-point velocity ``v_lp`` (µm/s) and the parameters ``p`` (mu0, a, b, Dc, k and the
    reference velocity V0, lab units)."""
    v0 = p["V0"]
    ln_v = (mu - p["mu0"] - p["b"] * omega) / p["a"]  # ln(V/V0)
    v = v0 * ops.exp(ln_v)
    dmu = p["k"] * (v_lp - v)
    if law == "aging":
        domega = v0 / p["Dc"] * ops.exp(-omega) - v / p["Dc"]
    elif law == "slip":
        domega = -v / p["Dc"] * (ln_v + omega)
    else:
        raise ValueError(f"rate-and-state law {law!r} is not known; choose one of {', '.join(RSF_LAWS)}")
    return dmu, domega


_INTEGRATOR_OPTIONS = dict(abstol=1e-11, reltol=1e-9, max_num_steps=500000)


def _rhs_function(law: str) -> tuple:
    """(x, q, ode) symbols of the law's right-hand side; q = (mu0, a, b, Dc, k, V0, V_lp)."""
    x = ca.SX.sym("x", 2)
    q = ca.SX.sym("q", 7)
    p = dict(zip(("mu0", "a", "b", "Dc", "k", "V0"), [q[i] for i in range(6)]))
    dmu, dom = rsf_rhs(law, x[0], x[1], q[6], p)
    return x, q, ca.vertcat(dmu, dom)


def transient_function(law: str, drive: VelocityDrive, time_s: np.ndarray) -> ca.Function:
    """mu(theta) -> μ at every time of ``time_s``, θ = (mu0, a, b, Dc, k), from steady
    sliding at the drive's first velocity (which is the reference velocity V0).

    One IDAS integration per stretch of constant load-point velocity, each reporting the
    state at that stretch's samples (IDAS: BDF, the law is stiff since V reacts to μ over
    a displacement a/k); derivatives of the Function are IDAS's forward sensitivities.
    Built once per data set and reused for every evaluation."""
    t = np.asarray(time_s, float)
    if t.ndim != 1 or t.size == 0 or np.any(np.diff(t) <= 0):
        raise ValueError("time_s must be a non-empty increasing 1-D array")
    t0 = float(drive.times_s[0])
    if t[0] < t0 - 1e-12:
        raise ValueError(f"time {t[0]} s lies before the drive's start {t0} s")
    xs, qs, ode = _rhs_function(law)
    theta = ca.MX.sym("theta", 5)
    v0 = float(drive.velocities_um_per_s[0])
    x = ca.vertcat(theta[0], 0.0)
    bounds = [t0] + [float(c) for c in drive.times_s[1:] if t0 < c < t[-1]] + [float(t[-1])]
    pieces = []
    if t[0] <= t0 + 1e-12:
        pieces.append(x[0])
    for j in range(len(bounds) - 1):
        s, e = bounds[j], bounds[j + 1]
        if e <= s:
            continue
        sel = (t > s + 1e-12) & (t <= e + 1e-12)
        grid = np.union1d(t[sel] - s, [e - s])
        F = ca.integrator(f"rsf_{law}_{j}", "idas", dict(x=xs, p=qs, ode=ode), 0.0, list(grid),
                          _INTEGRATOR_OPTIONS)
        v = float(drive.velocity_at(np.array([0.5 * (s + e)]))[0])
        X = F(x0=x, p=ca.vertcat(theta, v0, v))["xf"]
        if sel.any():
            cols = np.searchsorted(grid, t[sel] - s - 1e-12)
            pieces.append(X[0, list(map(int, cols))].T)
        x = X[:, -1]
    mu = ca.vertcat(*pieces)
    return ca.Function(f"rsf_mu_{law}", [theta], [mu], ["theta"], ["mu"])


def simulate_rsf(law: str, params: Mapping, drive: VelocityDrive, time_s: np.ndarray) -> np.ndarray:
    """μ at the times ``time_s`` (increasing, from ``drive.times_s[0]`` on), from steady
    sliding at the drive's first velocity, the reference velocity of μ0. ``params``:
    mu0, a, b, Dc (µm), k (1/µm)."""
    if law not in RSF_LAWS:
        raise ValueError(f"rate-and-state law {law!r} is not known; choose one of {', '.join(RSF_LAWS)}")
    f = transient_function(law, drive, time_s)
    return np.asarray(f([float(params[n]) for n in RSF_PARAMETERS])).ravel()
