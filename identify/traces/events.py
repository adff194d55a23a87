"""Slip events of a recorded run: step phase, plateaus, slips and the run's regime.

What a trace holds (``shared/MODEL.md``): the puller advances in steps of Δxp at the
instants t_n = (n + φ)/fp, n = 1, 2, ... (φ ∈ [0, 1) the run's step phase; a simulated
run has φ = 0); the camera measures the spring elongation e = xp − x. With the number
of steps n(t_j) taken by each frame time,

    b_j = Δxp·n(t_j) − e_j = x(t_j) − xp0 + noise,

the block position: a non-decreasing staircase that jumps up at slips, plus Gaussian
camera noise σ (≈ 90 nm, larger than a step). Everything here works on ``b``:

step phase
    The frames only sample the step clock at a few phases, so only a few distinct
    sequences n(t_j) exist (m of them for m frames per step). Each candidate (the
    midpoint of each gap between frame phases, and φ = 0) is scored by the sum of
    squared first differences of b, each clipped at 4σ̂ so that long slips count alike
    for every candidate. The right phase leaves a flat staircase; a wrong one leaves
    ±Δxp spikes at the frames it mis-counts. Slips shorter than 4σ̂ are not clipped and
    a wrong phase can shorten them by Δxp, so once plateaus are known the score is
    taken again over the pairs of frames inside them (away from their edges), and the
    run is segmented again if the phase changes. φ = 0 wins ties (its step labels may
    differ from the midpoint's by one; lengths, peaks and rests do not). A phase in the
    trace metadata (``step_phase``) is used as given.
segmentation
    Optimal partitioning of b into constant-mean segments (PELT: Killick, Fearnhead &
    Eckley 2012) with the Gaussian cost (residual sum of squares, O(1) per segment
    from cumulative sums) and the penalty β = 2·σ̂²·ln(n)·c per segment, c = 1.5 (see
    :data:`PENALTY_FACTOR`). Then: (1) neighbouring segments whose levels differ by
    less than ``min_z`` standard errors are merged, least significant first, until all
    differences are significant; (2) runs of very short segments (≤ 2 frames in all)
    between two plateaus are frames caught inside a slip (their level lies between the
    plateaus) or outliers: they are excluded (``plateau_of_frame = -1``) and the
    plateaus on either side become neighbours; (3) significant negative jumps (the
    block should only move forward) are kept and reported in ``warnings``; (4) each
    slip boundary moves to the best split between two frames that straddle a step
    (the block can only start moving at a step), unless a split inside a step period
    fits better by more than 9σ̂² of RSS (a slip delayed by its creep nucleation); the
    best other step-aligned split and its extra RSS are kept with the slip, for the fit
    to try where the frames leave the step ambiguous.
    (5) a block that seems to move within its plateaus (backward: a too small step in
    the metadata, or a drift of the elongation; forward: a drift the other way, or
    creep while it sticks) cuts every plateau into pieces: when that speed is
    significant (:data:`TREND_SIGMAS`; forward, only below a tenth of the puller
    speed) the segmentation is repeated on b detrended by it, with a warning;
    everything else keeps b as given.
trigger step
    A slip starts at a step instant, and the block sits at its old level on every frame
    before that step. The trigger step of a slip is n(t) of the first frame after the
    slip (the last step that frame has seen), or of the first frame inside the slip if
    a frame caught it moving. When the camera takes fewer than one frame per step the
    slip can have started at any step since the last pre-slip frame and the trigger is
    the latest of them (a warning says so). At high fp a creep nucleation (0.1–1 ms
    with A > 0) can delay the fast slip past the first frame after its step; that frame
    still shows the old level and the trigger then comes out one step late.

regime
    ``no-slip`` with fewer than 2 slips; ``unresolved`` when the saw-tooth is not
    resolved: the block moves within its plateaus at more than a quarter of the puller
    speed (:attr:`RunEvents.creep_ratio`: creep or stepping, whose ramp PELT cuts into
    pieces), the inner plateaus are mostly shorter than 3 frames, or the noise-corrected
    σ·√12 slip length is below 2σ̂; else ``stick-slip``.

The reduced analysis of the paper (σ·√12 per run, Eq. 8, Eq. 9 fits) is in
:mod:`identify.traces.reduced`; every :class:`RunEvents` carries its run's
:class:`~identify.traces.reduced.ReducedRun`.

Where each part lives: the step phase in :mod:`identify.traces.step_phase`, the
segmentation and the noise estimate in :mod:`identify.traces.plateaus`, the plateau levels,
slips and trigger alternatives in :mod:`identify.traces.slips`. This module chains them
(:func:`extract_events`), holds the result (:class:`RunEvents`) and names the regime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identify.jsonio import jsonable as _jsonable
from identify.traces.io import Trace

# (``X as X``: names of the parts split out of this module stay importable from it)
from identify.traces.plateaus import MAD_TO_SIGMA as MAD_TO_SIGMA
from identify.traces.plateaus import (
    MAX_INSIDE_FRAMES,
    MIN_PLATEAU_FRAMES,
    PENALTY_FACTOR,
    creep_ratio,
    pelt,
    robust_noise,
    trend_segments,
)
from identify.traces.plateaus import NOISE_FLOOR_STEPS as NOISE_FLOOR_STEPS
from identify.traces.plateaus import TREND_SIGMAS as TREND_SIGMAS
from identify.traces.reduced import reduced_run
from identify.traces.slips import AMBIGUOUS_RSS as AMBIGUOUS_RSS
from identify.traces.slips import empty_slips, measure_slips, plateau_table, slip_warnings, trigger_alternatives
from identify.traces.step_phase import CLIP_SIGMAS as CLIP_SIGMAS
from identify.traces.step_phase import MAX_PHASE_CANDIDATES as MAX_PHASE_CANDIDATES
from identify.traces.step_phase import MAX_PROFILED_PHASES as MAX_PROFILED_PHASES
from identify.traces.step_phase import PHASE_TIE as PHASE_TIE
from identify.traces.step_phase import PHASE_TOLERANCE as PHASE_TOLERANCE
from identify.traces.step_phase import PhasedRun, estimate_step_phase, segment_at_step_phase, step_counts

__all__ = [
    "MAX_INSIDE_FRAMES",
    "PENALTY_FACTOR",
    "REGIMES",
    "RunEvents",
    "estimate_step_phase",
    "extract_events",
    "pelt",
    "robust_noise",
    "step_counts",
]

CREEP_RATIO_LIMIT = 0.25
"""A run whose block moves during its plateaus at more than this fraction of the puller
speed (:attr:`RunEvents.creep_ratio`) is creeping, not sticking: ``unresolved``."""

REGIMES = ("stick-slip", "unresolved", "no-slip")


# ----------------------------------------------------------------------------- result
_PLATEAU_KEYS = ("first_frame", "last_frame", "n_frames", "level_m", "level_se_m", "mean_puller_m")
_SLIP_KEYS = (
    "trigger_step",
    "trigger_time_s",
    "slip_length_m",
    "slip_length_se_m",
    "peak_elongation_m",
    "rest_steps",
    "rest_time_s",
    "z",
    "frames_inside",
    "alt_trigger_step",
    "alt_margin",
)


@dataclass
class RunEvents:
    """The events of one run (see the module docstring for how they are found).

    Attributes
    ----------
    trace : Trace
        The run.
    noise_m : float
        Camera noise σ̂, m: 1.4826·MAD/√2 of the first differences of b between frames
        of the same plateau (or the value passed to :func:`extract_events`).
    step_phase : float
        Step phase φ ∈ [0, 1): steps at (n + φ)/fp.
    steps : ndarray of int, shape (n_frames,)
        n(t_j), the number of steps taken by each frame time.
    puller_m : ndarray, shape (n_frames,)
        Δxp·n(t_j) = xp − xp0, m.
    block_m : ndarray, shape (n_frames,)
        b_j = puller_m − elongation = x − xp0 (+ noise), m.
    plateau_of_frame : ndarray of int, shape (n_frames,)
        Plateau index of each frame, −1 for excluded frames (inside a slip, outliers).
    plateaus : dict of ndarray, each of length P
        ``first_frame``, ``last_frame`` (inclusive), ``n_frames``, ``level_m`` (mean of
        b), ``level_se_m`` (σ̂/√n), ``mean_puller_m``.
    slips : dict of ndarray, each of length P − 1 (slip i between plateaus i and i+1)
        ``trigger_step`` (int), ``trigger_time_s`` ((trigger_step + φ)/fp),
        ``slip_length_m`` (level_{i+1} − level_i), ``slip_length_se_m``,
        ``peak_elongation_m`` (Δxp·trigger_step − level_i: the elongation just after
        the triggering step), ``rest_steps`` (trigger_step_i − trigger_step_{i−1};
        trigger_step_0 for the first), ``rest_time_s`` (rest_steps/fp), ``z`` (signed
        slip length / its standard error), ``frames_inside`` (excluded frames between
        the plateaus), ``alt_trigger_step`` and ``alt_margin`` (the best other
        step-aligned split of the frames and how much worse it fits, σ² of RSS; −1 and
        inf where there is none: below :data:`AMBIGUOUS_RSS` the fit tries it).
    regime : str
        ``stick-slip``; ``unresolved`` (no saw-tooth above the noise: slips too small,
        creep, or plateaus mostly shorter than 3 frames); ``no-slip`` (< 2 slips).
    reduced : ReducedRun
        The run's reduced analysis (:func:`identify.traces.reduced.reduced_run`).
    warnings : list of str
    creep_ratio, creep_ratio_se : float
        Mean block speed within the plateaus after the first slip (the slope of b
        fitted per plateau of ≥ 3 frames, averaged with the plateaus' durations as
        weights) over the puller speed fp·Δxp, and its standard error: 0 for a block
        at rest between slips, 1 for a block that follows the puller (creep or
        stepping, where PELT cuts the ramp of b into short pieces). NaN without such
        plateaus.
    segmentation_trend_m_per_s : float
        Speed removed from b before the plateaus were found (negative: the block seemed
        to move backward within its plateaus; positive: forward, :data:`TREND_SIGMAS`);
        0 when none was
        significant. The slips' lengths and z are those of the b as given, so with long
        rests a slip found on the detrended b can show a smaller z.
    """

    trace: Trace
    noise_m: float
    step_phase: float
    steps: np.ndarray
    puller_m: np.ndarray
    block_m: np.ndarray
    plateau_of_frame: np.ndarray
    plateaus: dict
    slips: dict
    regime: str
    reduced: Any = None
    warnings: list = field(default_factory=list)
    creep_ratio: float = math.nan
    creep_ratio_se: float = math.nan
    segmentation_trend_m_per_s: float = 0.0

    @property
    def n_slips(self) -> int:
        return len(self.slips["trigger_step"])

    @property
    def n_plateaus(self) -> int:
        return len(self.plateaus["level_m"])

    @property
    def step_size(self) -> float:
        return self.trace.step_size

    def model_elongation(self, time_s: np.ndarray | None = None) -> np.ndarray:
        """The noise-free staircase model of the elongation at ``time_s`` (default the
        frame times), m: Δxp·n(t) − level of the plateau the block sits on at t (the
        block jumps at the trigger step of each slip). Frames before the first frame
        take the first level."""
        tr = self.trace
        t = tr.time_s if time_s is None else np.asarray(time_s, float)
        n = step_counts(t, tr.step_frequency, self.step_phase)
        lv = self.plateaus["level_m"]
        # plateau index = number of slips triggered by t
        idx = np.searchsorted(self.slips["trigger_step"], n, side="right")
        return self.step_size * n - lv[np.clip(idx, 0, len(lv) - 1)]

    def to_json(self) -> dict:
        """The events as JSON-ready lists (SI, units in the keys)."""
        tr = self.trace
        out = dict(
            name=tr.name,
            n_frames=len(tr),
            n_slips=self.n_slips,
            regime=self.regime,
            noise_m=self.noise_m,
            step_phase=self.step_phase,
            step_frequency_Hz=tr.step_frequency,
            step_size_m=tr.step_size,
            plateaus={k: self.plateaus[k] for k in _PLATEAU_KEYS},
            slips={k: self.slips[k] for k in _SLIP_KEYS},
            excluded_frames=np.flatnonzero(self.plateau_of_frame < 0),
            creep_ratio=self.creep_ratio,
            creep_ratio_se=self.creep_ratio_se,
            segmentation_trend_m_per_s=self.segmentation_trend_m_per_s,
            reduced=self.reduced.to_json() if self.reduced is not None else None,
            warnings=list(self.warnings),
        )
        return _jsonable(out)

    def report(self) -> str:
        """Plain-text summary of the run's events."""
        tr = self.trace
        s = self.slips
        lines = [
            (
                f"Events of {tr.name}: {len(tr)} frames, fp = {tr.step_frequency:g} Hz, "
                f"k = {tr.spring_constant:g} N/m, Nb = {tr.normal_load * 1e6:.4g} µN"
            ),
            (
                f"  regime {self.regime}; {self.n_slips} slips; {self.n_plateaus} plateaus; "
                f"noise σ = {self.noise_m * 1e9:.1f} nm; step phase φ = {self.step_phase:.3f}"
            ),
        ]
        n_ex = int((self.plateau_of_frame < 0).sum())
        if n_ex:
            lines.append(f"  {n_ex} frame(s) excluded (inside slips or outliers)")
        if self.n_slips:
            sl = s["slip_length_m"] * 1e6
            pk = s["peak_elongation_m"] * 1e6
            lines.append(
                f"  slip length {sl.mean():.4f} µm (min {sl.min():.4f}, max {sl.max():.4f}); "
                f"peak elongation {pk.mean():.4f} µm"
            )
            if self.n_slips > 1:
                rs = s["rest_steps"][1:]
                lines.append(
                    f"  rest {rs.mean():.1f} steps ({rs.mean() / tr.step_frequency * 1e3:.2f} ms), "
                    f"min {rs.min()}, max {rs.max()}"
                )
        if self.reduced is not None:
            r = self.reduced
            lines.append(
                f"  reduced: δ̄ = σ·√12 = {r.slip_sqrt12_m * 1e6:.4f} µm "
                f"(noise-corrected {r.slip_sqrt12_corrected_m * 1e6:.4f} µm), "
                f"μs(σ√12) = {r.mu_s_sqrt12:.4f}, μs(events) = {r.mu_s_events:.4f}"
            )
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- main
def extract_events(trace: Trace, *, noise_m: float | None = None, min_z: float = 5.0) -> RunEvents:
    """Find the step phase, plateaus and slips of a run (module docstring).

    Parameters
    ----------
    trace : Trace
        The run (its ``step_frequency``, ``step_size`` and, if present, metadata key
        ``step_phase`` are used).
    noise_m : float, optional
        Camera noise σ, m; default estimated from the trace.
    min_z : float
        Smallest significance ``|Δlevel|/se`` of a slip (and of any level change kept).

    Returns
    -------
    RunEvents

    Raises
    ------
    ValueError
        If ``noise_m`` or ``min_z`` is not a positive finite number, or the metadata's
        ``step_phase`` is not a number in [0, 1).
    """
    _check_options(noise_m, min_z)
    t, fp, dx = trace.time_s, trace.step_frequency, trace.step_size
    warnings: list[str] = []
    frames_per_step = trace.frame_rate / fp
    if frames_per_step < 0.999:
        warnings.append(_sparse_frames_warning(frames_per_step))
    run = segment_at_step_phase(trace, noise_m, min_z, frames_per_step, warnings)
    segs, sigma, trend, seg_warnings = trend_segments(
        t, run.b, run.steps, run.segments, run.sigma, run.warnings, noise_m, min_z, frames_per_step, fp, dx
    )
    warnings += seg_warnings
    if trend:
        warnings.append(_trend_warning(trend, fp, dx))
    plateau_of_frame, plateaus = plateau_table(run.b, run.puller, segs, sigma, len(trace))
    if len(segs) >= 2:
        slips = _slips(run, segs, plateaus, sigma, trend, frames_per_step, trace, warnings)
    else:
        slips = empty_slips()
    ev = RunEvents(
        trace=trace,
        noise_m=float(sigma),
        step_phase=float(run.phi),
        steps=run.steps,
        puller_m=run.puller,
        block_m=run.b,
        plateau_of_frame=plateau_of_frame,
        plateaus=plateaus,
        slips=slips,
        regime="no-slip",
        reduced=None,
        warnings=warnings,
    )
    ev.creep_ratio, ev.creep_ratio_se = creep_ratio(t, run.b, segs, sigma, fp * dx)
    ev.segmentation_trend_m_per_s = trend
    ev.reduced = reduced_run(trace, ev)
    ev.regime = _classify(ev)
    ev.reduced.regime = ev.regime
    return ev


def _check_options(noise_m: float | None, min_z: float) -> None:
    """Refuse a noise or a significance that is not a positive finite number."""
    if noise_m is not None and not (math.isfinite(noise_m) and noise_m > 0):
        raise ValueError(f"noise_m = {noise_m!r}: must be a positive finite number (m)")
    if not (math.isfinite(min_z) and min_z > 0):
        raise ValueError(f"min_z = {min_z!r}: must be a positive finite number")


def _sparse_frames_warning(frames_per_step: float) -> str:
    """The warning of a camera slower than the steps: a trigger can be steps late."""
    return (
        f"fewer than one frame per step ({frames_per_step:.3g}): a slip's trigger step is "
        "the last step before its first post-slip frame and may be up to "
        f"{math.ceil(1 / frames_per_step) - 1} step(s) late"
    )


def _trend_warning(trend: float, fp: float, dx: float) -> str:
    """The warning of a block that seemed to move within its plateaus, whose speed was
    removed before segmenting (:data:`TREND_SIGMAS`)."""
    ratio = abs(trend) / (fp * dx)
    if trend < 0:
        return (
            f"inside its plateaus the block moves backward at {ratio:.3f} of the puller "
            f"speed ({trend * 1e9:.4g} nm/s): the elongation rises faster than the metadata's step of "
            f"{dx * 1e9:.4g} nm per step (a wrong step size) or drifts; the plateaus were found on the "
            "block position detrended by that speed"
        )
    return (
        f"inside its plateaus the block moves forward at {ratio:.3f} of the puller speed "
        f"({trend * 1e9:.4g} nm/s): the elongation drifts down, or the block creeps while it sticks; "
        "the plateaus were found on the block position detrended by that speed"
    )


def _slips(run: PhasedRun, segs, plateaus, sigma, trend, frames_per_step, trace, warnings) -> dict:
    """The slips between the plateaus (at least two), with their alternative triggers
    found on the b the plateaus were found on; their oddities go to ``warnings``."""
    t, fp, dx = trace.time_s, trace.step_frequency, trace.step_size
    slips = measure_slips(plateaus, run.steps, sigma, run.phi, fp, dx)
    b_seg = run.b - trend * (t - t[0]) if trend else run.b  # what the plateaus were found on
    slips["alt_trigger_step"], slips["alt_margin"] = trigger_alternatives(
        b_seg, run.steps, segs, sigma, frames_per_step
    )
    warnings += slip_warnings(slips, plateaus, run.steps)
    return slips


def plateaus_move(ev: RunEvents) -> bool:
    """The block moves during the plateaus the segmentation found at more than
    :data:`CREEP_RATIO_LIMIT` of the puller speed (3 standard errors clear of it)."""
    cr, cse = ev.creep_ratio, ev.creep_ratio_se
    return bool(math.isfinite(cr) and cr > CREEP_RATIO_LIMIT and cr > 3 * cse)


def _classify(ev: RunEvents) -> str:
    """Regime from the data (see :class:`RunEvents`)."""
    if ev.n_slips < 2:
        return "no-slip"
    cr, cse = ev.creep_ratio, ev.creep_ratio_se
    if plateaus_move(ev):
        ev.warnings.append(
            f"the block moves during its plateaus at {cr:.2f} ± {cse:.2f} of the puller speed: "
            "creep or stepping, the slips found are pieces of a ramp"
        )
        return "unresolved"
    if math.isfinite(cr) and cr > 0.05 and cr > 5 * cse:
        ev.warnings.append(
            f"the block creeps during sticks at {cr:.2f} ± {cse:.2f} of the puller speed"
        )
    inner = ev.plateaus["n_frames"][1:-1]
    if inner.size and np.median(inner) < MIN_PLATEAU_FRAMES:
        return "unresolved"
    dc = ev.reduced.slip_sqrt12_corrected_m
    if not (math.isfinite(dc) and dc >= 2.0 * ev.noise_m):
        return "unresolved"
    return "stick-slip"
