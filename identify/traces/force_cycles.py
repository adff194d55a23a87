"""Stick-slip or inertial oscillation, from a force record under a constant-velocity drive.

The spring force F (here normalised by the normal load, F/N) and the drive's velocity V
give the slider's own velocity: e = x_lp − x, so v = V − (N/k)·dF/dt. While it sticks,
the force rises at the drive's rate k·V/N exactly; a slip is the slider outrunning the
drive. The data decide the regime by how long the slider stays stuck:

* **stick-slip**: a sawtooth, the force rising most of the time while the slider is
  stuck (v < ``stuck_below``·V) and falling in brief slips;
* **inertial**: an oscillation, the force rising about half the time;
* **steady**: sliding with the force flat within its noise.

Impulsive noise (single-sample spikes, as paper-on-paper recordings have) is taken out
by a running median before the derivative; the derivative is a local least-squares slope
over a window a small fraction of the typical cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import median_filter
from scipy.signal import savgol_filter

from identify.jsonio import SavedResult

__all__ = ["CycleAnalysis", "analyze_cycles", "cycles_of_trace"]


@dataclass
class CycleAnalysis(SavedResult):
    """What the force record shows: ``regime``; the share of the time the force rises
    (``rising_fraction``) and the slider's ``stuck_fraction`` of the time; per slip its
    force ``drops`` and the ``periods`` between slip starts (or an oscillation's); the
    force's ``rise_rate`` while stuck against the drive's ``drive_rate`` (k·V/N, per s);
    ``noise`` of the force (per sample, impulses excluded) and its ``swing`` (robust
    peak-to-peak)."""

    name: str
    regime: str
    rising_fraction: float
    stuck_fraction: float
    drive_rate: float
    rise_rate: float
    noise: float
    swing: float
    slip_times_s: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    drops: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    periods: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    @property
    def mean_drop(self) -> float:
        return float(np.mean(self.drops)) if self.drops.size else float("nan")

    @property
    def mean_period(self) -> float:
        return float(np.mean(self.periods)) if self.periods.size else float("nan")

    def report(self) -> str:
        lines = [f"{self.name}: {self.regime} (the force rises {100 * self.rising_fraction:.0f} % of the time)",
                 f"    slider stuck {100 * self.stuck_fraction:.0f} % of the time; force rises at "
                 f"{self.rise_rate:.4g}/s while stuck (the drive's k·V/N = {self.drive_rate:.4g}/s)",
                 f"    force swing {self.swing:.3g} (robust peak to peak), noise {self.noise:.2g} per sample"]
        if self.regime == "inertial" and self.periods.size:
            lines.append(f"    oscillation: {self.periods.size} cycles, period {self.mean_period:.4g} ± "
                         f"{np.std(self.periods):.2g} s (sd)")
        if self.drops.size:
            lines.append(f"    {self.drops.size} slips: force drop {self.mean_drop:.4g} ± {np.std(self.drops):.2g} "
                         f"(sd), recurrence {self.mean_period:.4g} ± {np.std(self.periods):.2g} s (sd)")
        return "\n".join(lines)

    def to_json(self) -> dict:
        return dict(kind="cycle_analysis", name=self.name, regime=self.regime,
                    rising_fraction=self.rising_fraction, stuck_fraction=self.stuck_fraction,
                    drive_rate=self.drive_rate, rise_rate=self.rise_rate, noise=self.noise, swing=self.swing,
                    mean_drop=self.mean_drop, mean_period=self.mean_period, slip_times_s=self.slip_times_s,
                    drops=self.drops, periods=self.periods)

    def plot(self, ax=None):
        """Force drop against the reload time after it (:func:`identify.plots.transient.plot_cycles`)."""
        from identify.plots.transient import plot_cycles

        return plot_cycles(self, ax=ax)

    @classmethod
    def from_dict(cls, d: dict) -> CycleAnalysis:
        arr = {k: np.asarray(d.get(k) or [], float) for k in ("slip_times_s", "drops", "periods")}
        return cls(name=d["name"], regime=d["regime"], rising_fraction=float(d["rising_fraction"]),
                   stuck_fraction=float(d["stuck_fraction"]),
                   drive_rate=float(d["drive_rate"]), rise_rate=float(d["rise_rate"]), noise=float(d["noise"]),
                   swing=float(d["swing"]), **arr)


_STEADY_SWING = 1e-4  # force/N: a swing below this is steady sliding even in noiseless (simulated) data
_FINE = 21  # samples of the slip detector's slope (10 ms at 2 kHz): short beside a slip cycle


def _slips(t: np.ndarray, Fm: np.ndarray, noise: float, drive_rate: float):
    """Slip episodes: runs where the force falls faster than the noise allows (5 standard
    errors of a ``_FINE``-sample slope, and faster than the drive raises it), joined
    across gaps of under ``_FINE`` samples; (start times, force drops from the level
    before the run to the level after it)."""
    dt = float(np.median(np.diff(t)))
    m = _FINE
    slope = savgol_filter(Fm, m, 1, deriv=1, delta=dt, mode="nearest")
    se = noise * np.sqrt(12.0) / (m * dt * np.sqrt(m))
    idx = np.flatnonzero(slope < -max(5 * se, drive_rate))
    if idx.size == 0:
        return np.zeros(0), np.zeros(0)
    breaks = np.flatnonzero(np.diff(idx) > m)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    before = np.array([np.max(Fm[max(a - m, 0):a + 1]) for a in starts])
    after = np.array([np.min(Fm[b:min(b + m + 1, len(Fm))]) for b in ends])
    return t[starts], before - after


def analyze_cycles(time_s: np.ndarray, force_norm: np.ndarray, *, drive_rate: float, name: str = "run",
                   stuck_below: float = 0.3) -> CycleAnalysis:
    """The regime and the slip cycles of a force record (module docstring).

    Parameters
    ----------
    time_s, force_norm : the samples (force over the normal load, so that the drive's
        rate k·V/N is per second).
    drive_rate : k·V/N, the rate at which the force rises while the slider sticks (1/s).
    stuck_below : the slider counts as stuck below ``stuck_below``·V.

    The regime is read from the share of the time the force rises (a sawtooth rises most
    of the time and falls in brief slips; an oscillation rises half the time): stick-slip
    at 0.65 or more, inertial below 0.6, steady when the force swings less than ten times
    its noise (or than 1e-4 of the normal load, for noiseless records). The slope that
    decides it is taken over a window long enough for its standard error to be a tenth of
    the drive's rate, at most 5 % of the time the drive needs to raise the force by its
    swing, at least 5 samples.
    """
    t, F = np.asarray(time_s, float), np.asarray(force_norm, float)
    if t.size < 50 or t.shape != F.shape or np.any(np.diff(t) <= 0):
        raise ValueError(f"{name}: time_s and force_norm must be one length (>= 50), time increasing")
    if not drive_rate > 0:
        raise ValueError(f"{name}: drive_rate = {drive_rate!r} must be > 0 (k·V/N, per s)")
    dt = float(np.median(np.diff(t)))
    d = np.diff(F)
    noise = float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2))
    Fm = median_filter(F, size=5, mode="nearest")  # single-sample impulses out
    lo, hi = np.percentile(Fm, [2, 98])
    swing = float(hi - lo)
    # the slope's window: long enough that its standard error is a tenth of the drive's
    # rate (so "stuck" is not noise), short beside the time the drive needs to raise the
    # force by its swing (5 % of it: so that slips do not blur into the loading)
    n_noise = (noise * np.sqrt(12.0) / (0.1 * drive_rate * dt)) ** (2.0 / 3.0)
    n = max(5, int(round(min(n_noise, 0.05 * swing / drive_rate / dt))) | 1)
    slope = savgol_filter(Fm, n, 1, deriv=1, delta=dt, mode="nearest")
    rising = float(np.mean(slope > 0))
    stuck = (1.0 - slope / drive_rate) < stuck_below  # the slider's velocity over the drive's
    rise = float(np.median(slope[stuck])) if stuck.any() else float("nan")
    if swing < max(10 * noise, _STEADY_SWING):
        regime = "steady"
    elif rising >= 0.65:
        regime = "stick-slip"
    elif rising < 0.6:
        regime = "inertial"
    else:
        regime = "intermediate"
    if regime in ("stick-slip", "intermediate"):
        starts, drops = _slips(t, Fm, noise, drive_rate)
        keep = drops > 5 * noise
        starts, drops = starts[keep], drops[keep]
        periods = np.diff(starts)
    else:
        starts, drops = np.zeros(0), np.zeros(0)
        periods = _oscillation_periods(t, savgol_filter(Fm, n, 1, mode="nearest"), 3 * noise) \
            if regime == "inertial" else np.zeros(0)
    return CycleAnalysis(name, regime, rising, float(np.mean(stuck)), float(drive_rate), rise, noise, swing,
                         starts, drops, periods)


def _oscillation_periods(t: np.ndarray, f: np.ndarray, hysteresis: float) -> np.ndarray:
    """Times between upward crossings of the force's running mean (over ~10 cycles' worth
    of samples is not known here: the median of the whole record), with a hysteresis
    band so that noise does not count as crossings."""
    mid = float(np.median(f))
    low, high = f < mid - hysteresis, f > mid + hysteresis
    # an upward crossing: a sample above the band whose last sample outside the band was below it
    outside = np.nonzero(low | high)[0]
    above = high[outside]
    ups = outside[1:][above[1:] & ~above[:-1]]
    return np.diff(np.asarray(t, float)[ups])


def cycles_of_trace(trace, **options) -> CycleAnalysis:
    """:func:`analyze_cycles` of a continuously driven trace at one constant velocity:
    the force over the normal load is k·e/N, and the drive's rate k·V/N."""
    drive = trace.drive
    if drive is None or len(set(drive.velocities_um_per_s)) != 1:
        raise ValueError(f"run {trace.name!r}: the cycle analysis needs a drive at one constant velocity "
                         f"({'a stepper' if drive is None else 'velocity steps'} given)")
    k, n = trace.spring_constant, trace.normal_load
    v = drive.velocities_um_per_s[0] * 1e-6
    return analyze_cycles(trace.time_s, trace.elongation * k / n, drive_rate=k * v / n, name=trace.name, **options)
