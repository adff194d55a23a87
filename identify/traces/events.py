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
    (5) a block that seems to move backward within its plateaus (a too small step in
    the metadata, or a drift of the elongation) cuts every plateau into pieces: when
    that speed is significant (:data:`BACKWARD_SIGMAS`) the segmentation is repeated on
    b detrended by it, with a warning; everything else keeps b as given.
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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identify.jsonio import jsonable as _jsonable
from identify.traces.io import Trace
from identify.traces.reduced import reduced_run

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

PENALTY_FACTOR = 1.5
"""c in the PELT penalty β = 2·σ̂²·ln(n)·c.

2·σ²·ln n is the Schwarz (BIC) penalty of a mean change with known variance (a
location and a level per change point). On pure noise the best single split of n
frames gains ≈ σ²·2·ln n in RSS (maximum of ~n correlated χ²₁ statistics), so c = 1
lets a few false change points through on long traces; c = 1.5 asks a new segment to
gain 3·σ²·ln n (≈ 26 σ² at n = 5000, a 5σ jump between long plateaus), which matches
the ``min_z = 5`` significance used afterwards. False splits that remain are merged by
that significance test; real slips longer than ~4σ between plateaus of ≥ 10 frames
clear it easily."""

MAX_INSIDE_FRAMES = 2
"""At most this many consecutive frames between two plateaus are taken as caught inside
one slip (a slip lasts ~40 µs plus its creep nucleation, far less than a frame interval
below fp = 1 kHz)."""

MIN_PLATEAU_FRAMES = 3
"""A segment needs this many frames to be a plateau that can bound a slip's inside
frames; a run whose plateaus are mostly shorter has no resolved saw-tooth."""

CLIP_SIGMAS = 4.0
"""First differences of b beyond this many σ̂ are clipped in the step-phase score."""

CREEP_RATIO_LIMIT = 0.25
"""A run whose block moves during its plateaus at more than this fraction of the puller
speed (:attr:`RunEvents.creep_ratio`) is creeping, not sticking: ``unresolved``."""

NOISE_FLOOR_STEPS = 1e-3
"""σ̂ never goes below this many steps (46 pm), nor below 1e-7 of the range of b: on a
noiseless trace the segmentation then sees exact plateaus, and the cumulative sums of
PELT keep their rounding far below the penalty."""

PHASE_TOLERANCE = 0.01
"""Frame phases (in step periods) closer than this are one cluster: no candidate step
phase is tried between them (rounded or jittered timestamps)."""

PHASE_TIE = 2.0
"""χ² units by which a step phase's segmentation must beat φ = 0 (and the earlier
candidates) in :func:`_profile_phase`."""

MAX_PROFILED_PHASES = 8
"""Up to this many candidate step phases (frames per step) each get a full segmentation
(:func:`_profile_phase`); above it the first-difference estimate is iterated."""

MAX_PHASE_CANDIDATES = 64
"""Above this many distinct frame phases (frame rate not a multiple of fp) the step
phase is searched on a uniform grid of this many candidates."""

REGIMES = ("stick-slip", "unresolved", "no-slip")

MAD_TO_SIGMA = 1.482602218505602  # 1/Φ⁻¹(3/4): MAD of a Gaussian -> σ


# ----------------------------------------------------------------------------- helpers
def robust_noise(b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """σ of white noise on a piecewise-constant signal from its first differences.

    Parameters
    ----------
    b : ndarray
        Signal, m.
    mask : ndarray of bool, optional
        Which first differences (len(b) − 1) to use; default all.

    Returns
    -------
    float
        1.4826·MAD(diff(b))/√2, m (0 for fewer than 2 differences). Rare jumps do not
        move the median, so slips need not be removed first.
    """
    d = np.diff(np.asarray(b, float))
    if mask is not None:
        d = d[mask]
    if d.size < 2:
        return 0.0
    return float(MAD_TO_SIGMA * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def step_counts(time_s: np.ndarray, step_frequency: float, phase: float) -> np.ndarray:
    """n(t): number of puller steps taken by each time, steps at (n + φ)/fp, n ≥ 1.

    A frame exactly at a step instant (within 1e-9 of a period) counts the step as
    taken, as the simulator does.
    """
    n = np.floor(np.asarray(time_s, float) * step_frequency - phase + 1e-9)
    return np.maximum(n, 0).astype(np.int64)


def _phase_candidates(time_s: np.ndarray, fp: float) -> np.ndarray:
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
        Which first differences to score (default all). :func:`extract_events` passes
        the pairs inside plateaus, away from their edges: slips shorter than 4σ̂ are
        not clipped, and as they happen at step crossings a wrong phase can shorten
        them by Δxp, which on runs with many small slips offsets the spikes it adds.

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
    cands = _phase_candidates(time_s, step_frequency)
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


def _profile_phase(t, e, fp, dx, cands, phi0, noise_m, min_z, frames_per_step) -> float:
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
    penalty = 2.0 * math.log(max(t.size, 2)) * PENALTY_FACTOR
    # φ = 0 first: the phases of the gap that wraps past 0 differ only in how the steps
    # are labelled (and in the clamp of n ≥ 0 at the start), so they must tie with it
    order = [0.0] + [c for c in [phi0, *cands] if c != 0.0]
    best, best_cost = 0.0, None
    for phi in order:
        steps = step_counts(t, fp, phi)
        b = dx * steps - e
        segs, _, _ = _segment_run(b, steps, sigma, min_z, frames_per_step, noise_floor=floor)
        rss = sum(float(((b[q.frames] - b[q.frames].mean()) ** 2).sum()) for q in segs) / sigma**2
        left_out = t.size - sum(q.n for q in segs)
        cost = rss + penalty * len(segs) + CLIP_SIGMAS**2 * left_out
        if best_cost is None or cost < best_cost - PHASE_TIE:
            best, best_cost = float(phi), cost
    return best % 1.0


def pelt(y: np.ndarray, penalty: float, scale: float = 1.0) -> np.ndarray:
    """Change points of the mean of ``y`` by PELT with the Gaussian (RSS) cost.

    Parameters
    ----------
    y : ndarray
        Signal.
    penalty : float
        β, added per segment, in units of ``scale``² (i.e. β = 2·ln(n)·c for a signal
        whose noise σ equals ``scale``).
    scale : float
        The signal is divided by this (and centred) before the cumulative sums, which
        keeps their rounding well below β.

    Returns
    -------
    ndarray of int
        Segment starts, ascending, beginning with 0 (segment i is
        ``y[starts[i]:starts[i+1]]``).
    """
    y = np.asarray(y, float)
    n = y.size
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    z = (y - np.median(y)) / (scale if scale > 0 else 1.0)
    s1 = np.concatenate([[0.0], np.cumsum(z)])
    s2 = np.concatenate([[0.0], np.cumsum(z * z)])
    F = np.empty(n + 1)
    F[0] = -penalty
    last = np.zeros(n + 1, dtype=np.int64)
    cand = np.zeros(1, dtype=np.int64)
    for t in range(1, n + 1):
        length = t - cand
        seg = s1[t] - s1[cand]
        cost = (s2[t] - s2[cand]) - seg * seg / length
        fc = F[cand] + cost
        i = int(np.argmin(fc))
        F[t] = fc[i] + penalty
        last[t] = cand[i]
        # PELT pruning (K = 0 for the RSS cost): s can never again be optimal when
        # F(s) + C(s, t) > F(t)
        keep = cand[fc <= F[t]]
        cand = np.append(keep, t)
    starts = []
    t = n
    while t > 0:
        t = int(last[t])
        starts.append(t)
    return np.array(starts[::-1], dtype=np.int64)


# ----------------------------------------------------------------------------- segments
@dataclass
class _Seg:
    """A run of frames (indices, possibly with gaps where frames were excluded)."""

    frames: np.ndarray

    @property
    def n(self) -> int:
        return int(self.frames.size)


def _levels(b, segs):
    return np.array([b[s.frames].mean() for s in segs])


def _merge_insignificant(b: np.ndarray, segs: list[_Seg], sigma: float, min_z: float) -> list[_Seg]:
    """Merge neighbours whose levels differ by less than ``min_z`` standard errors,
    the least significant pair first, until every neighbour pair is significant."""
    segs = list(segs)
    if len(segs) < 2:
        return segs
    sums = [float(b[s.frames].sum()) for s in segs]
    ns = [s.n for s in segs]

    def z_of(i):  # between i and i+1
        d = sums[i + 1] / ns[i + 1] - sums[i] / ns[i]
        se = sigma * math.sqrt(1.0 / ns[i] + 1.0 / ns[i + 1])
        return abs(d) / se if se > 0 else (math.inf if d != 0 else 0.0)

    zs = [z_of(i) for i in range(len(segs) - 1)]
    while zs:
        i = int(np.argmin(zs))
        if zs[i] >= min_z:
            break
        segs[i] = _Seg(np.concatenate([segs[i].frames, segs[i + 1].frames]))
        sums[i] += sums[i + 1]
        ns[i] += ns[i + 1]
        del segs[i + 1], sums[i + 1], ns[i + 1], zs[i]
        if i < len(zs):
            zs[i] = z_of(i)
        if i > 0:
            zs[i - 1] = z_of(i - 1)
    return segs


def _exclude_short(b: np.ndarray, segs: list[_Seg]) -> tuple[list[_Seg], list[int], int]:
    """Drop runs of short segments (≤ MAX_INSIDE_FRAMES frames in all) between two
    plateaus (≥ MIN_PLATEAU_FRAMES frames).

    Returns the kept segments, the excluded frame indices and how many of the excluded
    runs were *not* between the levels of their plateaus (outliers, not slip frames).
    """
    lv = _levels(b, segs)
    long_ = np.array([s.n >= MIN_PLATEAU_FRAMES for s in segs])
    keep = np.ones(len(segs), bool)
    excluded: list[int] = []
    outliers = 0
    i = 0
    while i < len(segs):
        if long_[i]:
            i += 1
            continue
        j = i
        while j < len(segs) and not long_[j]:
            j += 1
        # segments i..j-1 are short; bounded by plateaus i-1 and j?
        total = sum(segs[k].n for k in range(i, j))
        if i > 0 and j < len(segs) and total <= MAX_INSIDE_FRAMES:
            lo, hi = sorted((lv[i - 1], lv[j]))
            for k in range(i, j):
                keep[k] = False
                excluded.extend(segs[k].frames.tolist())
            if not all(lo <= lv[k] <= hi for k in range(i, j)):
                outliers += 1
        i = j
    return [s for s, k in zip(segs, keep) if k], excluded, outliers


def _split_rss(y: np.ndarray) -> np.ndarray:
    """RSS of the two-mean fit of ``y`` split before index k, for k = 1..len(y)-1."""
    c1 = np.cumsum(y)
    c2 = np.cumsum(y * y)
    n = y.size
    k = np.arange(1, n)
    left = c2[:-1] - c1[:-1] ** 2 / k
    r1 = c1[-1] - c1[:-1]
    r2 = c2[-1] - c2[:-1]
    right = r2 - r1**2 / (n - k)
    return left + right


def _split_window(b, steps, a, c, sigma, frames_per_step):
    """The splits of two neighbouring segments' frames within two steps of their
    boundary: (frames, current split k0, splits ks, their RSS in σ², whether each falls
    between two steps); None when frames were excluded between them (a slip with
    inside frames) or there is no split to consider."""
    if a[-1] + 1 != c[0]:
        return None
    w = max(2, round(2 * frames_per_step))
    f = np.concatenate([a, c])
    k0 = a.size
    lo, hi = max(1, k0 - w), min(f.size - 1, k0 + w)
    if hi < lo:
        return None
    y = (b[f] - b[f].mean()) / sigma
    ks = np.arange(lo, hi + 1)
    return f, k0, ks, _split_rss(y)[lo - 1 : hi], steps[f[ks]] > steps[f[ks - 1]]


def _snap_to_steps(b, steps, segs, sigma, frames_per_step):
    """Move each slip boundary to the best split between two frames that straddle a
    step, unless the data prefer a split inside a step period by more than 9σ² of RSS
    (a slip delayed past the next frame by its creep nucleation).

    The block can only start moving at a step, so a boundary between two frames of the
    same step period is, for a fast slip, a noisy frame assigned to the wrong plateau.
    """
    out = list(segs)
    for i in range(len(out) - 1):
        win = _split_window(b, steps, out[i].frames, out[i + 1].frames, sigma, frames_per_step)
        if win is None:
            continue
        f, k0, ks, rss, at_step = win
        if not at_step.any():
            continue
        k_free = ks[int(np.argmin(rss))]
        j = int(np.argmin(np.where(at_step, rss, np.inf)))
        k_step = ks[j]
        k = k_step if rss[j] - rss.min() <= 9.0 else k_free
        if k != k0 and 0 < k < f.size:
            out[i] = _Seg(f[:k])
            out[i + 1] = _Seg(f[k:])
    return out


AMBIGUOUS_RSS = 9.0
"""A slip boundary whose best other step-aligned split fits the frames within this much
RSS (σ², a likelihood ratio of e^4.5) is ambiguous: noise on the frames next to a slip
can make the split a step late. The fit then tries the alternative against the whole
model (:func:`identify.fitting.sequence.ambiguous_triggers`): measured on an OTS run
(k = 20.3 N/m, 30 µN, 30 Hz, 90 nm), one slip detected a step late (margin 1.6 σ²)
shifted μmin by −11 % and A by +83 %, 9 standard errors, through the chain of slips
after it."""


def _trigger_alternatives(b, steps, segs, sigma, frames_per_step):
    """Per boundary between consecutive segments: (the step of the best other split
    that also falls between two steps, its extra RSS in σ²); (−1, inf) where there is
    none (frames excluded inside the slip, or no other step boundary within reach)."""
    alt = np.full(max(len(segs) - 1, 0), -1, np.int64)
    margin = np.full(max(len(segs) - 1, 0), np.inf)
    for i in range(len(segs) - 1):
        win = _split_window(b, steps, segs[i].frames, segs[i + 1].frames, sigma, frames_per_step)
        if win is None:
            continue
        f, k0, ks, rss, at_step = win
        other = at_step & (ks != k0)
        if not other.any():
            continue
        j = int(np.argmin(np.where(other, rss, np.inf)))
        alt[i] = int(steps[f[ks[j]]])
        margin[i] = float(rss[j] - rss[k0 - ks[0]])
    return alt, margin


def _inner_pairs(segs, n_frames: int, margin: int = 0) -> np.ndarray:
    """Mask of first differences (j, j+1) with both frames in the same segment and at
    least ``margin`` frames from its ends."""
    mask = np.zeros(max(n_frames - 1, 0), dtype=bool)
    for s in segs:
        f = s.frames
        if margin:
            f = f[margin:-margin]
        if f.size > 1:
            ok = np.diff(f) == 1
            mask[f[:-1][ok]] = True
    return mask


def _segment_run(b, steps, noise_m, min_z, frames_per_step, noise_floor):
    """Segment b; without a given noise, re-estimate σ from the pairs of frames inside
    plateaus and segment again while that moves σ by more than 5 %."""
    n_frames = b.size
    floor = max(1e-7 * float(np.ptp(b)), noise_floor)
    sigma = noise_m if noise_m is not None else max(robust_noise(b), floor)
    for _ in range(3):
        segs, _, seg_warnings = _segment(b, sigma, min_z)
        segs = _snap_to_steps(b, steps, segs, sigma, frames_per_step)
        if noise_m is not None:
            break
        same = _inner_pairs(segs, n_frames)
        new = max(robust_noise(b, same), floor) if same.sum() >= 10 else sigma
        converged = abs(new - sigma) <= 0.05 * sigma
        sigma = new
        if converged:
            break
    return segs, float(sigma), seg_warnings


def _segment(b: np.ndarray, sigma: float, min_z: float) -> tuple[list[_Seg], list[int], list[str]]:
    """Plateaus and excluded frames of b (steps 0-2 of the module docstring)."""
    n = b.size
    warnings: list[str] = []
    penalty = 2.0 * math.log(max(n, 2)) * PENALTY_FACTOR
    starts = pelt(b, penalty, scale=sigma)
    bounds = np.append(starts, n)
    segs = [_Seg(np.arange(bounds[i], bounds[i + 1])) for i in range(len(starts))]
    segs = _merge_insignificant(b, segs, sigma, min_z)
    excluded_all: list[int] = []
    for _ in range(5):  # excluding frames can make neighbours mergeable, and so on
        segs, excluded, outliers = _exclude_short(b, segs)
        if outliers:
            warnings.append(
                f"{outliers} short run(s) of frames outside the levels of their neighbouring "
                "plateaus were excluded as outliers"
            )
        excluded_all.extend(excluded)
        before = len(segs)
        segs = _merge_insignificant(b, segs, sigma, min_z)
        if not excluded and len(segs) == before:
            break
    return segs, sorted(excluded_all), warnings


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
        to move backward within its plateaus, :data:`BACKWARD_SIGMAS`); 0 when none was
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
def _empty_slips() -> dict:
    return dict(
        trigger_step=np.zeros(0, np.int64),
        trigger_time_s=np.zeros(0),
        slip_length_m=np.zeros(0),
        slip_length_se_m=np.zeros(0),
        peak_elongation_m=np.zeros(0),
        rest_steps=np.zeros(0, np.int64),
        rest_time_s=np.zeros(0),
        z=np.zeros(0),
        frames_inside=np.zeros(0, np.int64),
        alt_trigger_step=np.zeros(0, np.int64),
        alt_margin=np.zeros(0),
    )


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
    if noise_m is not None and not (math.isfinite(noise_m) and noise_m > 0):
        raise ValueError(f"noise_m = {noise_m!r}: must be a positive finite number (m)")
    if not (math.isfinite(min_z) and min_z > 0):
        raise ValueError(f"min_z = {min_z!r}: must be a positive finite number")
    t = trace.time_s
    e = trace.elongation
    fp = trace.step_frequency
    dx = trace.step_size
    n_frames = len(trace)
    warnings: list[str] = []

    # -- step phase (from the first differences of b; then again from the pairs of
    #    frames inside the plateaus that phase gives, until it no longer changes)
    frames_per_step = trace.frame_rate / fp
    if frames_per_step < 0.999:
        warnings.append(
            f"fewer than one frame per step ({frames_per_step:.3g}): a slip's trigger step is "
            "the last step before its first post-slip frame and may be up to "
            f"{math.ceil(1 / frames_per_step) - 1} step(s) late"
        )
    meta_phase = trace.metadata.get("step_phase")
    if meta_phase is not None:
        try:
            phi = float(meta_phase)
        except (TypeError, ValueError):
            raise ValueError(
                f"{trace.name}: metadata step_phase = {meta_phase!r} is not a number"
            ) from None
        if not (0.0 <= phi < 1.0):
            raise ValueError(f"{trace.name}: metadata step_phase = {phi!r}: must lie in [0, 1)")
    else:
        phi, _ = estimate_step_phase(t, e, fp, dx)
    profiled = False
    if meta_phase is None:
        cands = _phase_candidates(t, fp)
        if 1 < cands.size <= MAX_PROFILED_PHASES:
            phi = _profile_phase(t, e, fp, dx, cands, phi, noise_m, min_z, frames_per_step)
            profiled = True
    tried = {phi}
    for attempt in range(4):
        steps = step_counts(t, fp, phi)
        puller = dx * steps
        b = puller - e
        segs, sigma, seg_warnings = _segment_run(
            b, steps, noise_m, min_z, frames_per_step, noise_floor=NOISE_FLOOR_STEPS * dx
        )
        if meta_phase is not None or profiled or attempt == 3:
            break
        inner = _inner_pairs(segs, n_frames, margin=2)
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
    segs, sigma, trend, seg_warnings = _backward_trend_segments(
        t, b, steps, segs, sigma, seg_warnings, noise_m, min_z, frames_per_step, fp, dx
    )
    warnings += seg_warnings
    if trend:
        warnings.append(
            f"inside its plateaus the block moves backward at {-trend / (fp * dx):.3f} of the puller "
            f"speed ({trend * 1e9:.4g} nm/s): the elongation rises faster than the metadata's step of "
            f"{dx * 1e9:.4g} nm per step (a wrong step size) or drifts; the plateaus were found on the "
            "block position detrended by that speed"
        )

    # -- plateaus
    P = len(segs)
    plateau_of_frame = np.full(n_frames, -1, dtype=np.int64)
    first = np.array([s.frames[0] for s in segs], dtype=np.int64)
    last = np.array([s.frames[-1] for s in segs], dtype=np.int64)
    nfr = np.array([s.n for s in segs], dtype=np.int64)
    level = np.array([b[s.frames].mean() for s in segs])
    mean_puller = np.array([puller[s.frames].mean() for s in segs])
    for p, s in enumerate(segs):
        plateau_of_frame[s.frames] = p
    plateaus = dict(
        first_frame=first,
        last_frame=last,
        n_frames=nfr,
        level_m=level,
        level_se_m=sigma / np.sqrt(nfr),
        mean_puller_m=mean_puller,
    )

    # -- slips
    if P >= 2:
        inside = np.array([int(first[i + 1] - last[i] - 1) for i in range(P - 1)], dtype=np.int64)
        trig_frame = np.where(inside > 0, last[:-1] + 1, first[1:])
        trigger = steps[trig_frame].astype(np.int64)
        length = np.diff(level)
        se = sigma * np.sqrt(1.0 / nfr[:-1] + 1.0 / nfr[1:])
        rest = np.diff(np.concatenate([[0], trigger]))
        slips = dict(
            trigger_step=trigger,
            trigger_time_s=(trigger + phi) / fp,
            slip_length_m=length,
            slip_length_se_m=se,
            peak_elongation_m=dx * trigger - level[:-1],
            rest_steps=rest.astype(np.int64),
            rest_time_s=rest / fp,
            z=length / se,
            frames_inside=inside,
        )
        b_seg = b - trend * (t - t[0]) if trend else b  # what the plateaus were found on
        slips["alt_trigger_step"], slips["alt_margin"] = _trigger_alternatives(b_seg, steps, segs, sigma,
                                                                              frames_per_step)
        neg = np.flatnonzero(length < 0)
        if neg.size:
            warnings.append(
                f"{neg.size} significant backward jump(s) of the block (the block should only "
                f"move forward), at frames {', '.join(str(int(first[i + 1])) for i in neg[:5])}"
                + (" ..." if neg.size > 5 else "")
            )
        late = np.flatnonzero(trigger <= steps[last[:-1]])
        if late.size:
            warnings.append(
                f"{late.size} slip(s) whose first post-slip frame saw no new step "
                "(trigger_step equals the step count of the last pre-slip frame)"
            )
    else:
        slips = _empty_slips()

    ev = RunEvents(
        trace=trace,
        noise_m=float(sigma),
        step_phase=float(phi),
        steps=steps,
        puller_m=puller,
        block_m=b,
        plateau_of_frame=plateau_of_frame,
        plateaus=plateaus,
        slips=slips,
        regime="no-slip",
        reduced=None,
        warnings=warnings,
    )
    ev.creep_ratio, ev.creep_ratio_se = _creep_ratio(t, b, segs, sigma, fp * dx)
    ev.segmentation_trend_m_per_s = trend
    ev.reduced = reduced_run(trace, ev)
    ev.regime = _classify(ev)
    ev.reduced.regime = ev.regime
    return ev


BACKWARD_SIGMAS = 3.0
"""A mean block speed within the plateaus this many standard errors below zero is not
friction (the block only moves forward): the metadata's step is too small or the
elongation drifts, and b, sloping inside every plateau, would be cut into pieces with
backward jumps. The plateaus are then found on b detrended by that speed."""


def _backward_trend_segments(t, b, steps, segs, sigma, seg_warnings, noise_m, min_z, frames_per_step, fp, dx):
    """Segments of b found after removing a significant backward speed within the
    plateaus (:data:`BACKWARD_SIGMAS`); (segs, sigma, speed removed in m/s or 0 if none,
    the warnings of the segmentation kept).

    The speed is measured on the undetrended b inside the current plateaus, so each pass
    gives the whole trend, not an increment; pieces of a cut plateau absorb part of it,
    hence a few passes until the plateaus stop changing. Only the partition changes:
    levels, slips and the fit keep b as the metadata give it, so a wrong step or a drift
    still shows in the fit's stick-phase slopes, where the diagnosis can name it."""
    trend = 0.0
    puller_speed = fp * dx
    for _ in range(4):
        cr, cse = _creep_ratio(t, b, segs, sigma, puller_speed)
        if not (math.isfinite(cr) and math.isfinite(cse) and cr < -BACKWARD_SIGMAS * cse):
            break
        new_trend = cr * puller_speed
        if trend and abs(new_trend - trend) <= 0.02 * abs(trend):
            break
        trend = new_trend
        detrended = b - trend * (t - t[0])
        new_segs, sigma, seg_warnings = _segment_run(
            detrended, steps, noise_m, min_z, frames_per_step, noise_floor=NOISE_FLOOR_STEPS * dx
        )
        same = len(new_segs) == len(segs) and all(np.array_equal(a.frames, c.frames) for a, c in zip(new_segs, segs))
        segs = new_segs
        if same:
            break
    return segs, sigma, trend, seg_warnings


def _creep_ratio(t, b, segs, sigma, puller_speed) -> tuple[float, float]:
    """Duration-weighted mean slope of b over the plateaus after the first, / fp·Δxp."""
    num = den = var = 0.0
    for s in segs[1:]:
        if s.n < MIN_PLATEAU_FRAMES:
            continue
        tt = t[s.frames]
        dt = tt - tt.mean()
        sxx = float(dt @ dt)
        if sxx <= 0:
            continue
        T = float(tt[-1] - tt[0])
        slope = float(dt @ (b[s.frames] - b[s.frames].mean())) / sxx
        num += T * slope
        den += T
        var += T * T * sigma * sigma / sxx
    if den <= 0:
        return math.nan, math.nan
    return num / den / puller_speed, math.sqrt(var) / den / puller_speed


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
