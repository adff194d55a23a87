"""Plateaus of the block position b: the segmentation of a run into constant levels.

PELT with the Gaussian cost and the penalty of :data:`PENALTY_FACTOR`; then the merging of
insignificant level changes, the exclusion of frames caught inside slips, the snapping of
slip boundaries to steps and, where the block seems to move within its plateaus,
the segmentation of b detrended by that speed (steps (1)–(5) of the segmentation in
:mod:`identify.traces.events`). With them, the robust noise estimate σ̂ the segmentation
works in, and the creep ratio (the block's speed within its plateaus).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FORWARD_TREND_LIMIT",
    "TREND_SIGMAS",
    "MAD_TO_SIGMA",
    "MAX_INSIDE_FRAMES",
    "MIN_PLATEAU_FRAMES",
    "NOISE_FLOOR_STEPS",
    "PENALTY_FACTOR",
    "Segment",
    "pelt",
    "robust_noise",
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

NOISE_FLOOR_STEPS = 1e-3
"""σ̂ never goes below this many steps (46 pm), nor below 1e-7 of the range of b: on a
noiseless trace the segmentation then sees exact plateaus, and the cumulative sums of
PELT keep their rounding far below the penalty."""

TREND_SIGMAS = 3.0
"""A mean block speed within the plateaus this many standard errors from zero cuts
every plateau into pieces: b slopes inside each one, and PELT takes the ramp for a
staircase. Backward it is not friction (the block only moves forward): the metadata's
step is too small or the elongation drifts. Forward it is a drift of the elongation the
other way, or the block creeping while it sticks. Either way the plateaus are then found
on b detrended by that speed (only the partition: levels and slips keep b as given)."""

FORWARD_TREND_LIMIT = 0.1
"""A forward speed within the plateaus is removed for the partition only below this
fraction of the puller speed. A camera's drift is far below it (50 nm/s against 1.4 µm/s
at 30 Hz: 0.036). Above it the speed is the block's own: small slips that the plateaus
cut across read 0.21 of the puller speed on a run of slips every five steps (20.3 N/m,
30 µN, 100 Hz), and removing it merged real slips there (37 for 46); a block that
follows the puller (creep or stepping) reads more."""

MAD_TO_SIGMA = 1.482602218505602  # 1/Φ⁻¹(3/4): MAD of a Gaussian -> σ


# ----------------------------------------------------------------------------- noise, PELT
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
class Segment:
    """A run of frames (indices, possibly with gaps where frames were excluded)."""

    frames: np.ndarray

    @property
    def n(self) -> int:
        """Number of frames."""
        return int(self.frames.size)


def _levels(b, segs):
    """Level (mean of b) of each segment."""
    return np.array([b[s.frames].mean() for s in segs])


def _merge_insignificant(b: np.ndarray, segs: list[Segment], sigma: float, min_z: float) -> list[Segment]:
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
        segs[i] = Segment(np.concatenate([segs[i].frames, segs[i + 1].frames]))
        sums[i] += sums[i + 1]
        ns[i] += ns[i + 1]
        del segs[i + 1], sums[i + 1], ns[i + 1], zs[i]
        if i < len(zs):
            zs[i] = z_of(i)
        if i > 0:
            zs[i - 1] = z_of(i - 1)
    return segs


SLOW_SLIP_FACTOR = 3.0
"""A run of short segments between two plateaus, longer than ``MAX_INSIDE_FRAMES``, is a
slow slip caught in several frames (a slip that lasts several steps: PELT, with a small
σ, gives each of its frames a level of its own) when its levels climb from one plateau
to the next and the block advanced this many times faster per puller step than it
does on average over the run; otherwise its segments stay (stepping: the block follows
each step)."""


SLOW_SLIP_SHARE = 1 / 8
"""In a run whose median segment is 24 frames or longer, a segment between the levels of
its neighbours and at most this share of the median long is looked at as a possible slow
slip's frames (which the noise groups in pieces of a few frames each), not taken as a
plateau outright; runs of shorter rests keep MIN_PLATEAU_FRAMES as the only test."""


def _slow_slip(b, segs, lv, i, j, steps) -> bool:
    """Whether short segments i..j-1, between plateaus i-1 and j, are one slow slip."""
    if steps is None or steps[-1] <= steps[0]:
        return False
    levels = [lv[i - 1], *lv[i:j], lv[j]]
    if not all(x < y for x, y in zip(levels, levels[1:])):
        return False
    mean_rate = (b[-1] - b[0]) / (steps[-1] - steps[0])  # the block's average advance per step
    elapsed = max(int(steps[segs[j].frames[0]] - steps[segs[i - 1].frames[-1]]), 1)
    return mean_rate > 0 and (lv[j] - lv[i - 1]) / elapsed > SLOW_SLIP_FACTOR * mean_rate


def _exclude_short(b: np.ndarray, segs: list[Segment], steps: np.ndarray | None = None
                   ) -> tuple[list[Segment], list[int], int]:
    """Drop runs of short segments (≤ MAX_INSIDE_FRAMES frames in all, or a slow slip's
    frames: :data:`SLOW_SLIP_FACTOR`) between two plateaus (≥ MIN_PLATEAU_FRAMES frames).

    Returns the kept segments, the excluded frame indices and how many of the excluded
    runs were *not* between the levels of their plateaus (outliers, not slip frames).
    """
    lv = _levels(b, segs)
    long_ = np.array([s.n >= MIN_PLATEAU_FRAMES for s in segs])
    if steps is not None and len(segs) >= 5:
        # in a run of long rests, a segment a small fraction of the typical one may be a
        # slow slip's frames grouped by the noise: short for the slow-slip test below
        brief = int(np.median([sg.n for sg in segs]) * SLOW_SLIP_SHARE)
        if brief >= MIN_PLATEAU_FRAMES:  # (rests of 24 frames and more: else as before)
            long_ &= np.array([s.n > brief for s in segs]) | ~np.array([
                0 < k < len(segs) - 1 and lv[k - 1] < lv[k] < lv[k + 1] for k in range(len(segs))])
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
        if i > 0 and j < len(segs) and (total <= MAX_INSIDE_FRAMES or _slow_slip(b, segs, lv, i, j, steps)):
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


def split_window(b, steps, a, c, sigma, frames_per_step):
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
        win = split_window(b, steps, out[i].frames, out[i + 1].frames, sigma, frames_per_step)
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
            out[i] = Segment(f[:k])
            out[i + 1] = Segment(f[k:])
    return out


def inner_pairs(segs, n_frames: int, margin: int = 0) -> np.ndarray:
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


def segment_run(b, steps, noise_m, min_z, frames_per_step, noise_floor):
    """Segment b; without a given noise, re-estimate σ from the pairs of frames inside
    plateaus and segment again while that moves σ by more than 5 %."""
    n_frames = b.size
    floor = max(1e-7 * float(np.ptp(b)), noise_floor)
    sigma = noise_m if noise_m is not None else max(robust_noise(b), floor)
    for _ in range(3):
        segs, _, seg_warnings = _segment(b, sigma, min_z, steps)
        segs = _snap_to_steps(b, steps, segs, sigma, frames_per_step)
        if noise_m is not None:
            break
        same = inner_pairs(segs, n_frames)
        new = max(robust_noise(b, same), floor) if same.sum() >= 10 else sigma
        converged = abs(new - sigma) <= 0.05 * sigma
        sigma = new
        if converged:
            break
    return segs, float(sigma), seg_warnings


def _segment(b: np.ndarray, sigma: float, min_z: float, steps: np.ndarray | None = None
             ) -> tuple[list[Segment], list[int], list[str]]:
    """Plateaus and excluded frames of b (steps 0-2 of the module docstring)."""
    n = b.size
    warnings: list[str] = []
    starts = pelt(b, pelt_penalty(n), scale=sigma)
    bounds = np.append(starts, n)
    segs = [Segment(np.arange(bounds[i], bounds[i + 1])) for i in range(len(starts))]
    segs = _merge_insignificant(b, segs, sigma, min_z)
    excluded_all: list[int] = []
    for _ in range(5):  # excluding frames can make neighbours mergeable, and so on
        segs, excluded, outliers = _exclude_short(b, segs, steps)
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


# ----------------------------------------------------------------------------- trend
def trend_segments(t, b, steps, segs, sigma, seg_warnings, noise_m, min_z, frames_per_step, fp, dx):
    """Segments of b found after removing a significant speed within the plateaus
    (:data:`TREND_SIGMAS`; forward only below :data:`FORWARD_TREND_LIMIT`); (segs,
    sigma, speed removed in m/s or 0 if none, the warnings of the segmentation kept).

    Why forward too: a camera whose zero drifts by 50 nm/s raised b by 160 nm over a
    3 s rest before a fresh contact's first slip, at 38 nm of noise; PELT cut that ramp
    into pieces whose steps of 50 nm passed as slips at z 5 to 7, six spurious slips among seven real ones (z 240 to
    400). Detrended, one remained: the run's first slip, which has no trigger residual to
    repair it by, and which cost the fit nothing visible (reduced χ² 1.036 at the truth).
    A forward speed is kept only below :data:`FORWARD_TREND_LIMIT` of the puller speed
    (small slips that the plateaus cut across read more, and removing it merged them),
    and where b without it, with the plateaus it leaves, costs less than b as given
    (:func:`_trend_explains_better`: slow slips' edge frames read less, and removing it
    cut more plateaus).

    The speed is measured on the undetrended b inside the current plateaus, so each pass
    gives the whole trend, not an increment; pieces of a cut plateau absorb part of it,
    hence a few passes until the plateaus stop changing. Only the partition changes:
    levels, slips and the fit keep b as the metadata give it, so a wrong step or a drift
    still shows in the fit's stick-phase slopes, where the diagnosis can name it."""
    trend = 0.0
    puller_speed = fp * dx
    given = segs, sigma, seg_warnings
    for _ in range(4):
        cr, cse = creep_ratio(t, b, segs, sigma, puller_speed)
        if not (math.isfinite(cr) and math.isfinite(cse) and abs(cr) > TREND_SIGMAS * cse
                and cr < FORWARD_TREND_LIMIT):
            break
        new_trend = cr * puller_speed
        if trend and abs(new_trend - trend) <= 0.02 * abs(trend):
            break
        trend = new_trend
        detrended = b - trend * (t - t[0])
        new_segs, sigma, seg_warnings = segment_run(
            detrended, steps, noise_m, min_z, frames_per_step, noise_floor=NOISE_FLOOR_STEPS * dx
        )
        same = len(new_segs) == len(segs) and all(np.array_equal(a.frames, c.frames) for a, c in zip(new_segs, segs))
        segs = new_segs
        if same:
            break
    if trend > 0 and not _trend_explains_better(t, b, trend, segs, given[0], given[1]):
        return *given[:2], 0.0, given[2]
    return segs, sigma, trend, seg_warnings


EXCLUDED_FRAME_COST = 16.0
"""χ² units a frame left out of every plateau costs a partition in :func:`partition_cost`
(a frame clipped at 4σ̂: the step phase's ``CLIP_SIGMAS`` squared)."""


def partition_cost(y, segs, sigma: float, n_frames: int) -> float:
    """The penalised cost of a partition of ``y``: the χ² of the frames about their
    plateau's level, the PELT penalty per plateau, :data:`EXCLUDED_FRAME_COST` per frame
    left out."""
    rss = sum(float(((y[q.frames] - y[q.frames].mean()) ** 2).sum()) for q in segs) / sigma**2
    left_out = n_frames - sum(q.n for q in segs)
    return rss + pelt_penalty(n_frames) * len(segs) + EXCLUDED_FRAME_COST * left_out


def pelt_penalty(n_frames: int) -> float:
    """The PELT penalty per segment in units of σ̂² (:data:`PENALTY_FACTOR`)."""
    return 2.0 * math.log(max(n_frames, 2)) * PENALTY_FACTOR


def _trend_explains_better(t, b, trend: float, segs, given, sigma: float) -> bool:
    """Whether b with a forward speed ``trend`` and the plateaus ``segs`` found without it
    costs less (:func:`partition_cost`, the speed one more parameter) than b as given with
    its plateaus ``given``.

    Why: the frames of slow slips (several frames each, at the plateaus' edges) raise the
    plateaus' mean slope too: 17 nm/s, 0.4 % of the puller speed at 3.8 standard errors,
    at 10 nm of noise. Removed, it cut b into 12 slips for 9, at a cost 1820 against
    1759 as given. (It does not tell small slips cut across from a drift: there the
    speed's size does, :data:`FORWARD_TREND_LIMIT`.)"""
    n = b.size
    with_trend = partition_cost(b - trend * (t - t[0]), segs, sigma, n) + pelt_penalty(n)
    return with_trend < partition_cost(b, given, sigma, n)


def creep_ratio(t, b, segs, sigma, puller_speed) -> tuple[float, float]:
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
