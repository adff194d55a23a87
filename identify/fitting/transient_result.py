"""The result of a rate-and-state transient fit: estimates in the names and units labs
use, a readable report, strict JSON that loads back, and its figure."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identify.jsonio import SavedResult

__all__ = ["TransientParameter", "TransientFitResult"]

_UNITS = dict(mu0="-", a="-", b="-", Dc="µm", k="1/µm", c="1/µm")
_Z95 = 1.959963984540054


@dataclass
class TransientParameter:
    """An estimate: ``value``; ``stderr_white``, the Gauss-Newton standard error as labs
    compute it (residuals taken as white noise); ``stderr``, the same widened for the
    residuals' serial correlation, which the 95 % interval uses; ``free``; ``init``."""

    name: str
    value: float
    stderr_white: float | None
    stderr: float | None
    free: bool
    init: float

    @property
    def ci95(self) -> tuple[float, float] | None:
        if self.stderr is None or not np.isfinite(self.stderr):
            return None
        return self.value - _Z95 * self.stderr, self.value + _Z95 * self.stderr


@dataclass
class TransientFitResult(SavedResult):
    """What :func:`identify.fitting.transient.fit_transient` found for one run."""

    run: str
    law: str
    parameters: dict
    n_samples: int
    rms: float
    noise: float
    scatter: float
    serial_inflation: float
    status: str
    success: bool
    nfev: int
    best_of: tuple
    correlations: dict
    reference_velocity_um_per_s: float
    drive: dict
    window_s: list
    time_s: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    mu: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    model: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    def __getitem__(self, name: str) -> TransientParameter:
        return self.parameters[name]

    @property
    def values(self) -> dict:
        return {n: p.value for n, p in self.parameters.items()}

    @property
    def misfit_ratio(self) -> float:
        """The residuals' RMS over the recording's scatter in steady sliding (what the
        data do while nothing changes, :func:`~identify.fitting.transient.steady_scatter`)."""
        return self.rms / self.scatter if self.scatter > 0 else float("nan")

    @property
    def misfit_white_ratio(self) -> float:
        """The residuals' RMS over the sample-to-sample noise (the instrument's)."""
        return self.rms / self.noise if self.noise > 0 else float("nan")

    def report(self) -> str:
        law = dict(aging="Dieterich (aging) law", slip="Ruina (slip) law").get(self.law, self.law)
        head = ("Fit converged" if self.success else f"Fit did not converge ({self.status})")
        lines = [
            f"{head}: {law}, run {self.run}",
            "[[Fit Statistics]]",
            f"    window             = {self.window_s[0]:.6g} .. {self.window_s[1]:.6g} s ({self.n_samples} samples)",
            "    load point         = " + ", ".join(
                f"{v:g} µm/s from {t:.6g} s" for t, v in zip(self.drive["times_s"], self.drive["velocities_um_per_s"])),
            f"    reference velocity = {self.reference_velocity_um_per_s:g} µm/s "
            "(mu0 is friction in steady sliding there)",
            f"    misfit (RMS)       = {self.rms:.3g}: {self.misfit_ratio:.2f} x the scatter in steady sliding "
            f"({self.scatter:.3g}), {self.misfit_white_ratio:.2f} x the sample-to-sample noise ({self.noise:.3g})",
            f"    serial correlation = intervals widened {self.serial_inflation:.2f} x for the residuals' lag-1 "
            "correlation (the ± column is the white-noise one, as labs report it)",
            f"    solver             = trust-region Gauss-Newton with IDAS sensitivities: {self.status}; "
            f"best found {self.best_of[0]} of {self.best_of[1]} starts",
            "[[Variables]]",
        ]
        for n, p in self.parameters.items():
            unit = "" if _UNITS[n] == "-" else f" {_UNITS[n]}"
            if not p.free and n == "c" and p.value == 0:
                continue  # (no trend asked for)
            if not p.free:
                lines.append(f"    {n:4s}: {p.value:.6g}{unit} (fixed)")
                continue
            ci = p.ci95
            ci_txt = f"  95% [{ci[0]:.6g}, {ci[1]:.6g}]" if ci else ""
            lines.append(f"    {n:4s}: {p.value:.6g} +/- {p.stderr_white:.2g}{unit}{ci_txt} (init = {p.init:.4g})")
        if "a" in self.parameters and "b" in self.parameters:
            a, b = self.parameters["a"].value, self.parameters["b"].value
            lines.append(f"    a-b : {a - b:+.4g} (velocity-{'strengthening' if a > b else 'weakening'})")
        big = {k: v for k, v in self.correlations.items() if abs(v) >= 0.5}
        if big:
            lines.append("[[Correlations]] (unreported correlations are < 0.500)")
            ordered = sorted(big.items(), key=lambda kv: -abs(kv[1]))
            lines += [f"    C({k.replace(',', ', ')}) = {v:+.4f}" for k, v in ordered]
        return "\n".join(lines)

    def to_json(self) -> dict:
        return dict(
            kind="transient_fit", run=self.run, law=self.law, n_samples=self.n_samples, rms=self.rms,
            noise=self.noise, scatter=self.scatter, misfit_ratio=self.misfit_ratio,
            misfit_white_ratio=self.misfit_white_ratio, serial_inflation=self.serial_inflation,
            status=self.status, success=self.success, nfev=self.nfev, best_of=list(self.best_of),
            correlations=self.correlations, reference_velocity_um_per_s=self.reference_velocity_um_per_s,
            drive=self.drive, window_s=self.window_s,
            parameters={n: dict(value=p.value, stderr_white=p.stderr_white, stderr=p.stderr, free=p.free,
                                init=p.init, ci95=list(p.ci95) if p.ci95 else None, unit=_UNITS[n])
                        for n, p in self.parameters.items()},
            samples=dict(time_s=self.time_s, mu=self.mu, model=self.model))

    @classmethod
    def from_dict(cls, d: dict) -> TransientFitResult:
        params = {n: TransientParameter(n, float(p["value"]), p.get("stderr_white"), p.get("stderr"), bool(p["free"]),
                                        float(p["init"])) for n, p in d["parameters"].items()}
        s = d.get("samples") or {}
        arr = {k: np.asarray(s.get(k) or [], float) for k in ("time_s", "mu", "model")}
        return cls(run=d["run"], law=d["law"], parameters=params, n_samples=int(d["n_samples"]), rms=float(d["rms"]),
                   noise=float(d["noise"]), scatter=float(d["scatter"]) if d.get("scatter") is not None
                   else float("nan"), serial_inflation=float(d["serial_inflation"]), status=d["status"],
                   success=bool(d["success"]), nfev=int(d["nfev"]), best_of=tuple(d["best_of"]),
                   correlations=dict(d["correlations"]),
                   reference_velocity_um_per_s=float(d["reference_velocity_um_per_s"]), drive=dict(d["drive"]),
                   window_s=list(d["window_s"]), **arr)

    def plot(self, ax=None):
        """Friction against time: the data, the fitted law, and (below, in the same axes'
        figure when ``ax`` is None) the residuals."""
        from identify.plots.transient import plot_transient_fit

        return plot_transient_fit(self, ax=ax)
