"""Plateau levels and slips measured on a run's segmentation.

A slip starts at a step instant, and the block sits at its old level on every frame
before that step. The trigger step of a slip is n(t) of the first frame after the slip
(the last step that frame has seen), or of the first frame inside the slip if a frame
caught it moving (see :mod:`identify.traces.events` for when it comes out late). With
it: the slip's length and its standard error, the peak elongation, the rest since the
previous trigger, and the best other step-aligned split of the frames
(:data:`AMBIGUOUS_RSS`).
"""

from __future__ import annotations

import numpy as np

from identify.traces.plateaus import Segment, split_window

__all__ = ["AMBIGUOUS_RSS"]

AMBIGUOUS_RSS = 9.0
"""A slip boundary whose best other step-aligned split fits the frames within this much
RSS (σ², a likelihood ratio of e^4.5) is ambiguous: noise on the frames next to a slip
can make the split a step late. The fit then tries the alternative against the whole
model (:func:`identify.fitting.mode_sequence.passes.ambiguous_triggers`): measured on an OTS run
(k = 20.3 N/m, 30 µN, 30 Hz, 90 nm), one slip detected a step late (margin 1.6 σ²)
shifted μmin by −11 % and A by +83 %, 9 standard errors, through the chain of slips
after it."""


def plateau_table(b: np.ndarray, puller: np.ndarray, segs: list[Segment], sigma: float, n_frames: int):
    """The plateau index of each frame (−1 where excluded) and the plateaus' columns of
    :attr:`identify.traces.events.RunEvents.plateaus` (frames, level of b, its se)."""
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
    return plateau_of_frame, plateaus


def measure_slips(plateaus: dict, steps: np.ndarray, sigma: float, phi: float, fp: float, dx: float) -> dict:
    """The slip between each two consecutive plateaus (at least two): trigger step and
    time, length and its se, peak elongation, rest, z and frames inside; the columns of
    :attr:`identify.traces.events.RunEvents.slips` but the alternative triggers."""
    first, last = plateaus["first_frame"], plateaus["last_frame"]
    nfr, level = plateaus["n_frames"], plateaus["level_m"]
    P = len(first)
    inside = np.array([int(first[i + 1] - last[i] - 1) for i in range(P - 1)], dtype=np.int64)
    trig_frame = np.where(inside > 0, last[:-1] + 1, first[1:])
    trigger = steps[trig_frame].astype(np.int64)
    length = np.diff(level)
    se = sigma * np.sqrt(1.0 / nfr[:-1] + 1.0 / nfr[1:])
    rest = np.diff(np.concatenate([[0], trigger]))
    return dict(
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


def trigger_alternatives(b, steps, segs, sigma, frames_per_step):
    """Per boundary between consecutive segments: (the step of the best other split
    that also falls between two steps, its extra RSS in σ²); (−1, inf) where there is
    none (frames excluded inside the slip, or no other step boundary within reach)."""
    alt = np.full(max(len(segs) - 1, 0), -1, np.int64)
    margin = np.full(max(len(segs) - 1, 0), np.inf)
    for i in range(len(segs) - 1):
        win = split_window(b, steps, segs[i].frames, segs[i + 1].frames, sigma, frames_per_step)
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


def slip_warnings(slips: dict, plateaus: dict, steps: np.ndarray) -> list[str]:
    """What is odd about the slips found: backward jumps of the block, and slips whose
    first post-slip frame saw no new step."""
    warnings = []
    first, last = plateaus["first_frame"], plateaus["last_frame"]
    length, trigger = slips["slip_length_m"], slips["trigger_step"]
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
    return warnings


def empty_slips() -> dict:
    """The slip columns of a run with fewer than two plateaus (no slip)."""
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
