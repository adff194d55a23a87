"""The step phase φ of a run: when the puller steps relative to the frames.

The frames sample the step clock at a few phases only, so a few candidate phases give
every distinct step count n(t_j); each is scored by the flatness of the block position
b = Δxp·n(t) − e (clipped first differences), or, with few candidates, by the whole
segmentation it leads to; the estimate is then refined from the pairs of frames inside
the plateaus it gives (the step-phase part of :mod:`identify.traces.events`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identify.traces.io import Trace
from identify.traces.plateaus import (
    NOISE_FLOOR_STEPS,
    Segment,
    inner_pairs,
    partition_cost,
    robust_noise,
    segment_run,
)

__all__ = [
    "CLIP_SIGMAS",
    "MAX_PHASE_CANDIDATES",
    "MAX_PROFILED_PHASES",
    "PHASE_TIE",
    "PHASE_TOLERANCE",
    "estimate_step_phase",
    "step_counts",
]

CLIP_SIGMAS = 4.0
"""First differences of b beyond this many σ̂ are clipped in the step-phase score."""

PHASE_TOLERANCE = 0.01
"""Frame phases (in step periods) closer than this are one cluster: no candidate step
phase is tried between them (rounded or jittered timestamps)."""

PHASE_TIE = 2.0
"""χ² units by which a step phase's segmentation must beat φ = 0 (and the earlier
candidates) in :func:`profile_phase`."""

MAX_PROFILED_PHASES = 8
"""Up to this many candidate step phases (frames per step) each get a full segmentation
(:func:`profile_phase`); above it the first-difference estimate is iterated."""

MAX_PHASE_CANDIDATES = 64
"""Above this many distinct frame phases (frame rate not a multiple of fp) the step
phase is searched on a uniform grid of this many candidates."""


def step_counts(time_s: np.ndarray, step_frequency: float, phase: float) -> np.ndarray:
    """n(t): number of puller steps taken by each time, steps at (n + φ)/fp, n ≥ 1.

    A frame exactly at a step instant (within 1e-9 of a period) counts the step as
    taken, as the simulator does.
    """
    n = np.floor(np.asarray(time_s, float) * step_frequency - phase + 1e-9)
    return np.maximum(n, 0).astype(np.int64)


def phase_candidates(time_s: np.ndarray, fp: float) -> np.ndarray:
    """Step phases that give every distinct sequence n(t_j) once (φ = 0 first).

    Frame phases u_j = frac(fp·t_j) closer than :data:`PHASE_TOLERANCE` of a period
    (rounded times, timestamp jitter) form one cluster; a candidate is the midpoint of
    each gap between clusters (circularly).
    """
    u = np.sort(np.mod(np.asarray(time_s, float) * fp, 1.0))
    gaps = np.diff(np.append(u, u[0] + 1.0))
    big = np.flatnonzero(gaps > PHASE_TOLERANCE)
    if big.size > MAX_PHASE_CANDIDATES:
        grid = (np.arange(MAX_PHASE_CANDIDATES) + 0.5) / MAX_PHASE_CANDIDATES
        return np.concatenate([[0.0], grid])
    if big.size <= 1:
        return (
            np.array([0.0])
            if big.size == 0
            else np.array([0.0, (u[big[0]] + gaps[big[0]] / 2) % 1.0])
        )
    mids = np.mod(u[big] + gaps[big] / 2, 1.0)
    return np.concatenate([[0.0], mids])


def estimate_step_phase(
    time_s: np.ndarray,
    elongation: np.ndarray,
    step_frequency: float,
    step_size: float,
    pair_mask: np.ndarray | None = None,
) -> tuple[float, dict]:
    """The step phase φ that makes b = Δxp·n(t) − e flattest.

    Parameters
    ----------
    time_s : ndarray
        Frame times, s.
    elongation : ndarray
        Elongation, m.
    step_frequency : float
        fp, Hz.
    step_size : float
        Δxp, m.
    pair_mask : ndarray of bool, shape (n − 1,), optional
        Which first differences to score (default all).
        :func:`~identify.traces.events.extract_events` passes the pairs inside
        plateaus, away from their edges: slips shorter than 4σ̂ are not clipped, and
        as they happen at step crossings a wrong phase can shorten them by Δxp, which
        on runs with many small slips offsets the spikes it adds.

    Returns
    -------
    phi : float
        Estimated phase in [0, 1): the midpoint of the gap between frame phases that
        gives the flattest b (every phase in that gap fits the data equally), or 0 when
        φ = 0 fits as well as the best midpoint (the simulator's default). The phase is
        only known to within its gap; where the gap wraps past 0 its two sides label
        the steps one apart, which changes trigger_step by one but no slip length,
        peak elongation or rest.
    info : dict
        ``candidates``, ``scores`` (clipped sums of squares, m²), ``sigma_m`` (the clip
        scale σ̂: the smallest robust noise over the candidates).
    """
    cands = phase_candidates(time_s, step_frequency)
    bs = [step_size * step_counts(time_s, step_frequency, p) - elongation for p in cands]
    sig = np.array([robust_noise(b) for b in bs])
    sigma = float(sig.min())
    clip = CLIP_SIGMAS * sigma
    scores = []
    for b in bs:
        d = np.diff(b)
        if pair_mask is not None:
            d = d[pair_mask]
        if clip > 0:
            d = np.clip(d, -clip, clip)
        scores.append(float(np.dot(d, d)))
    scores = np.array(scores)
    # φ = 0 (evaluated first) wins ties: the phases of one gap between frame phases
    # fit equally, and where a gap wraps past 0 its two sides label the steps one apart
    # (which no data can tell; slip lengths, peak elongations and rests do not change)
    best = int(np.argmin(scores))
    tol = 1e-9 * max(float(scores.max()), 1e-300)
    if scores[0] <= scores[best] + tol:
        best = 0
    phi = float(cands[best])
    return phi % 1.0, dict(candidates=cands, scores=scores, sigma_m=sigma)


def profile_phase(t, e, fp, dx, cands, phi0, noise_m, min_z, frames_per_step) -> float:
    """The step phase whose segmentation explains the frames best.

    Each candidate phase is segmented in full; its cost is the within-plateau χ² of b
    plus the PELT penalty per plateau plus CLIP_SIGMAS² per frame left out — the
    profile of the segmentation's likelihood over the phase. Every frame counts, and so
    does where the slips fall (under a wrong phase they fall between the frames of one
    step interval). The first-difference score of :func:`estimate_step_phase` uses pairs
    only; on a run with 12-frame plateaus, 90 nm noise and 46 nm steps it chose the
    wrong phase for 1 run in 50 (every trigger a step off); this profile chose right in
    all 50 (the margin there: 150 χ² units). ``phi0`` (the first-difference estimate)
    fixes the noise scale; a phase must beat the earlier ones (φ = 0 first, then
    ``phi0``) by ``PHASE_TIE`` to be chosen.
    """
    b0 = dx * step_counts(t, fp, phi0) - e
    floor = NOISE_FLOOR_STEPS * dx
    sigma = noise_m if noise_m is not None else max(robust_noise(b0), floor)
    # φ = 0 first: the phases of the gap that wraps past 0 differ only in how the steps
    # are labelled (and in the clamp of n ≥ 0 at the start), so they must tie with it
    order = [0.0] + [c for c in [phi0, *cands] if c != 0.0]
    best, best_cost = 0.0, None
    for phi in order:
        steps = step_counts(t, fp, phi)
        b = dx * steps - e
        segs, _, _ = segment_run(b, steps, sigma, min_z, frames_per_step, noise_floor=floor)
        cost = partition_cost(b, segs, sigma, t.size)
        if best_cost is None or cost < best_cost - PHASE_TIE:
            best, best_cost = float(phi), cost
    return best % 1.0


# ----------------------------------------------------------------------------- the run's phase
@dataclass
class PhasedRun:
    """The block position of a run at one step phase, and its plateaus."""

    phi: float
    steps: np.ndarray  # n(t_j)
    puller: np.ndarray  # Δxp·n(t_j), m
    b: np.ndarray  # puller − elongation, m
    segments: list[Segment]
    sigma: float  # noise σ̂ the segmentation used, m
    warnings: list[str]  # of the segmentation


def metadata_step_phase(trace: Trace) -> float | None:
    """The step phase the trace's metadata give (``step_phase``), None without one.

    Raises ValueError when it is not a number in [0, 1).
    """
    meta_phase = trace.metadata.get("step_phase")
    if meta_phase is None:
        return None
    try:
        phi = float(meta_phase)
    except (TypeError, ValueError):
        raise ValueError(
            f"{trace.name}: metadata step_phase = {meta_phase!r} is not a number"
        ) from None
    if not (0.0 <= phi < 1.0):
        raise ValueError(f"{trace.name}: metadata step_phase = {phi!r}: must lie in [0, 1)")
    return phi


def first_step_phase(t, e, fp, dx, noise_m, min_z, frames_per_step) -> tuple[float, bool]:
    """The first-difference estimate of φ, replaced by the segmentation profile
    (:func:`profile_phase`) when there are few candidates; (φ, whether it was profiled)."""
    phi, _ = estimate_step_phase(t, e, fp, dx)
    cands = phase_candidates(t, fp)
    if 1 < cands.size <= MAX_PROFILED_PHASES:
        return profile_phase(t, e, fp, dx, cands, phi, noise_m, min_z, frames_per_step), True
    return phi, False


def segment_at_phase(t, e, fp, dx, phi, noise_m, min_z, frames_per_step) -> PhasedRun:
    """b at step phase φ and its plateaus (:func:`~identify.traces.plateaus.segment_run`)."""
    steps = step_counts(t, fp, phi)
    puller = dx * steps
    b = puller - e
    segs, sigma, seg_warnings = segment_run(
        b, steps, noise_m, min_z, frames_per_step, noise_floor=NOISE_FLOOR_STEPS * dx
    )
    return PhasedRun(phi, steps, puller, b, segs, sigma, seg_warnings)


def segment_at_step_phase(
    trace: Trace, noise_m: float | None, min_z: float, frames_per_step: float, warnings: list[str]
) -> PhasedRun:
    """The run segmented at its step phase: the metadata's phase as given, or the profiled
    one; else the first-difference estimate, taken again from the pairs of frames inside
    the plateaus it gives until it no longer changes (a warning in ``warnings`` if it cycles).
    """
    t, e, fp, dx = trace.time_s, trace.elongation, trace.step_frequency, trace.step_size
    phi = metadata_step_phase(trace)
    fixed = phi is not None
    if not fixed:
        phi, fixed = first_step_phase(t, e, fp, dx, noise_m, min_z, frames_per_step)
    tried = {phi}
    for attempt in range(4):
        run = segment_at_phase(t, e, fp, dx, phi, noise_m, min_z, frames_per_step)
        if fixed or attempt == 3:
            break
        inner = inner_pairs(run.segments, len(trace), margin=2)
        if inner.sum() < 10:
            break
        new_phi, _ = estimate_step_phase(t, e, fp, dx, pair_mask=inner)
        if new_phi in tried:
            if new_phi != phi:  # cycling: keep the last segmentation, say so
                warnings.append(
                    "the step phase estimate is ambiguous (it cycles between candidates)"
                )
            break
        tried.add(new_phi)
        phi = new_phi
    return run
