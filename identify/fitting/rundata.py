"""One run prepared for the NLP: its plateaus (frame counts, means, the pooled
within-plateau staircase) for a given mode sequence, or its steady level for a run
that creeps. The mode sequence (trigger steps) decides which frames belong to which
plateau; :mod:`identify.fitting.mode_sequence.passes` rebuilds a run this way for every sequence it tries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from identify.model.scopes import device_label

__all__ = ["RunData", "SIGMA_FLOOR", "drop_frames", "make_run_data", "steps_between_triggers"]

SIGMA_FLOOR = 1e-12 / math.sqrt(12)  # m: rounding of the trace format's 6 decimals in µm


@dataclass
class RunData:
    """One run prepared for the NLP (numbers from its detected events)."""

    name: str
    kind: str  # "events" or "creep"
    k: float
    Nb: float
    fp: float
    step_nominal: float
    sigma: float  # frame noise, m
    n_frames: int
    # events runs: per plateau
    plateau_n: np.ndarray | None = None
    plateau_mean_e: np.ndarray | None = None  # m
    plateau_mean_steps: np.ndarray | None = None
    plateau_level0: np.ndarray | None = None  # data estimate of the block position, m
    plateau_mean_t: np.ndarray | None = None  # mean frame time, s (drift)
    frame_phases: np.ndarray | None = None  # distinct step phases of the frames (motion blur)
    phase_counts: np.ndarray | None = None  # plateaus × phases: frame counts
    s_nn: float = 0.0  # pooled within-plateau Σ(n − n̄)²
    slope_hat: float = 0.0  # pooled within-plateau staircase slope, m/step
    s_res: float = 0.0  # pooled within-plateau residual sum of squares, m²
    # frames around the slips as observations of their own (make_run_data's ``drops``)
    drops: bool = False
    drop_e: np.ndarray | None = None  # m
    drop_t: np.ndarray | None = None  # s
    drop_steps: np.ndarray | None = None  # n(t), steps taken by the frame's timestamp
    drop_phase: np.ndarray | None = None  # step phase u of the frame (fraction of the step interval)
    drop_slip: np.ndarray | None = None  # which of the run's slips (index into trigger_steps)
    drop_dt: np.ndarray | None = None  # s: timestamp less the slip's trigger step time
    drop_moving: np.ndarray | None = None  # s: the time the slip covers its length in (0: not known)
    # per slip
    trigger_steps: np.ndarray | None = None
    # creep runs
    steady_mean_e: float = float("nan")
    steady_se: float = float("nan")
    events: Any = None
    device: str = ""  # the trace's device, else its nominal spring constant (identify.model.scopes)
    span_s: float = float("nan")  # the last frame's time, s (the camera's random walk is a series over it)

    def stick_edge(self, values: dict) -> str | None:
        """Why this run sits on the stick threshold's knife edge, or None.

        With the stick option (v_stick > 0) a sliding block is held once slower than
        v_stick. When the puller is faster than that, a slip ends only if the block's
        speed dips below the threshold in the ripple the steps give it: at one set of
        parameters a slip stops within milliseconds, at a nearby one it turns into steady
        sliding over the whole arc, a jump in the slip length no gradient step can
        follow. Measured (README, the stick question): a 2.13 N/m, 20 µN, 300 Hz run (13.8 µm/s
        against 10 µm/s) made a 5-run fit crawl at step lengths ≤ 1e-2 because of it.
        """
        v_stick = float(values.get("v_stick", 0.0))
        v_pull = self.step_nominal * float(values.get("step_scale", 1.0)) * self.fp
        if self.kind != "events" or v_stick <= 0 or v_pull < v_stick:
            return None
        return (f"the puller's speed {v_pull * 1e6:.3g} µm/s is above the stick threshold "
                f"v_stick = {v_stick * 1e6:.3g} µm/s: whether a slip ends hangs on the block dipping "
                "below it between steps, which the parameters decide discontinuously (a slip stops "
                "within ms, or slides on); the fit may crawl and lean on this run")


def _resolved_slips(ev) -> bool:
    """Most of the block's travel happens in slips much longer than a puller step: the
    run is event-based even when the block also creeps between slips (the model as
    written has creep tails). A creeping block, cut by the segmentation into many small
    'slips' of a step or two, fails this."""
    d = np.asarray(ev.slips.get("slip_length_m", []), float)
    big = d > 10 * ev.trace.step_size
    return int(big.sum()) >= 2 and d[big].sum() > 0.5 * np.abs(d).sum()


def plateaus_from_triggers(ev, triggers: np.ndarray, moving_s: np.ndarray | None = None) -> np.ndarray:
    """Plateau index of every frame for given trigger steps: frames before trigger i's
    step belong to plateau i, later ones to plateau i + 1; frames while the block moves
    (from the trigger step for ``moving_s[i]`` seconds) are left out (−1)."""
    steps = ev.steps
    pof = np.searchsorted(np.asarray(triggers), steps, side="right").astype(int)
    if moving_s is not None and len(triggers):
        t = ev.trace.time_s
        fp = ev.trace.step_frequency
        t_trig = (np.asarray(triggers, float) + ev.step_phase) / fp
        k = np.clip(pof - 1, 0, len(triggers) - 1)
        inside = (pof >= 1) & (t >= t_trig[k]) & (t < t_trig[k] + np.asarray(moving_s)[k])
        pof[inside] = -1
    return pof


def steps_between_triggers(ev, v_stick: float) -> bool:
    """Under the stick option (``v_stick`` > 0) the model holds a block slower than
    v_stick, so a block that moves during its plateaus (:func:`identify.traces.events.plateaus_move`)
    moves by releases — a slip at a step — the detected triggers lack: the model of a
    run's events cannot follow it, not even at the truth. Measured (the withheld
    rejuvenation set, dc = 1 µm): its 2.13 N/m, 10 µN, 100 Hz run moves during its
    plateaus at 0.34 of the puller speed; fitted with its two stick-slip neighbours at
    the truth (only μmax free) χ² is 38 774 for 4148 degrees of freedom (reduced 9.3),
    against reduced 1.07 on the two alone. Without the option (v_stick = 0) the model
    has creep tails of its own, and such a run stays event-based (:func:`_resolved_slips`)."""
    from identify.traces.events import plateaus_move

    return bool(v_stick > 0 and ev.regime == "unresolved" and plateaus_move(ev))


def _levels(pof: np.ndarray, e: np.ndarray, steps: np.ndarray, dx: float, P: int) -> np.ndarray:
    """Data estimate of each plateau's block position, Δx·n̄ − ē over its frames (m); a
    plateau without frames takes its predecessor's (nothing moved the block that the
    frames saw)."""
    use = pof >= 0
    n = np.bincount(pof[use], minlength=P).astype(float)
    mean_e = np.bincount(pof[use], weights=e[use], minlength=P) / np.maximum(n, 1)
    mean_s = np.bincount(pof[use], weights=steps[use], minlength=P) / np.maximum(n, 1)
    level = dx * mean_s - mean_e
    for i in np.flatnonzero(n == 0):
        level[i] = level[i - 1] if i > 0 else 0.0
    return level


def _per_slip(values, slip: np.ndarray) -> np.ndarray:
    return np.zeros(slip.size) if values is None else np.asarray(values, float)[slip]


def drop_frames(ev, triggers: np.ndarray, moving_s: np.ndarray | None = None) -> tuple:
    """The frames a blurred exposure can carry a slip into, as observations of their own:
    those within one step period of a trigger step (an exposure up to a step period long
    reaches the slip from no further), less those while the block moves (from the
    trigger step for ``moving_s`` seconds, where the slip's own path, not the window,
    decides what they read) and those within reach of two slips.

    Returns (frame indices, their slip's index in ``triggers``)."""
    tr = ev.trace
    t = np.asarray(tr.time_s, float)
    trig = np.asarray(triggers, float)
    if not trig.size:
        return np.zeros(0, int), np.zeros(0, int)
    fp = tr.step_frequency
    t_s = (trig + ev.step_phase) / fp
    # slip i reaches the frames with t_s − 1/fp ≤ t < t_s + 1/fp
    lo = np.searchsorted(t_s, t - 1 / fp, side="right")
    hi = np.searchsorted(t_s, t + 1 / fp, side="right")
    slip = np.minimum(lo, len(t_s) - 1)
    use = hi - lo == 1
    if moving_s is not None:
        d = t - t_s[slip]
        use &= ~((d >= 0) & (d < np.asarray(moving_s, float)[slip]))
    idx = np.flatnonzero(use)
    return idx, slip[idx].astype(int)


def make_run_data(ev, triggers: np.ndarray | None = None, moving_s: np.ndarray | None = None,
                  v_stick: float = 0.0, drops: bool = False, ramp_s: np.ndarray | None = None) -> RunData:
    """The run for the NLP: its plateaus for the mode sequence ``triggers`` (default: the
    detected one), or its steady level where it has no resolvable slips — or, under the
    stick option ``v_stick`` > 0, where it steps between its triggers
    (:func:`steps_between_triggers`). With ``drops``, the frames around each slip
    (:func:`drop_frames`) leave the plateaus and become observations of their own, so
    that a blurred exposure straddling a slip can be seen (``FitOptions.drop_frames``);
    ``ramp_s``: the time each slip covers its length in (default its moving time), the
    path those frames' model takes for it."""
    tr = ev.trace
    # noiseless files still carry the print precision (1e-6 µm): uniform rounding error
    sigma = max(float(ev.noise_m), SIGMA_FLOOR)
    base = dict(name=tr.name, k=tr.spring_constant, Nb=tr.normal_load, fp=tr.step_frequency,
                step_nominal=tr.step_size, sigma=sigma, n_frames=len(tr.time_s), events=ev,
                device=device_label(tr.device, tr.spring_constant),
                span_s=float(np.max(tr.time_s)) if len(tr.time_s) else float("nan"))
    if (ev.regime != "stick-slip" and not _resolved_slips(ev)) or steps_between_triggers(ev, v_stick):
        # steady part: the second half of the run (after any loading transient)
        e = tr.elongation[len(tr.elongation) // 2:]
        se = math.sqrt(ev.noise_m**2 / max(len(e), 1) + (tr.step_size / math.sqrt(12)) ** 2)
        return RunData(kind="creep", steady_mean_e=float(np.mean(e)), steady_se=se, **base)
    if triggers is None:
        triggers = np.asarray(ev.slips["trigger_step"], int)
        pof = ev.plateau_of_frame
    else:
        pof = plateaus_from_triggers(ev, triggers, moving_s)
    steps = ev.steps.astype(float)
    e = tr.elongation
    P = len(triggers) + 1
    drop = {}
    level0 = _levels(pof, e, steps, tr.step_size, P)  # (the data's block positions, before any frame leaves)
    if drops:
        # (frames in the slow approach to the stop speed, within nanometres of the end, count)
        ramp = ramp_s if ramp_s is not None else moving_s
        idx, slip = drop_frames(ev, triggers, ramp)
        pof = pof.copy()
        pof[idx] = -1
        t_all = np.asarray(tr.time_s, float)
        t_s = (np.asarray(triggers, float)[slip] + ev.step_phase) / tr.step_frequency
        drop = dict(drops=True, drop_e=np.asarray(e, float)[idx], drop_t=t_all[idx], drop_steps=steps[idx],
                    drop_phase=np.mod(t_all[idx] * tr.step_frequency - ev.step_phase, 1.0), drop_slip=slip,
                    drop_dt=t_all[idx] - t_s,
                    drop_moving=_per_slip(ramp, slip))
    use = pof >= 0
    n = np.bincount(pof[use], minlength=P).astype(float)
    sum_e = np.bincount(pof[use], weights=e[use], minlength=P)
    sum_s = np.bincount(pof[use], weights=steps[use], minlength=P)
    mean_e, mean_s = sum_e / np.maximum(n, 1), sum_s / np.maximum(n, 1)
    de = e[use] - mean_e[pof[use]]
    ds = steps[use] - mean_s[pof[use]]
    s_nn, s_en, s_ee = float(ds @ ds), float(de @ ds), float(de @ de)
    slope = s_en / s_nn if s_nn > 0 else tr.step_size
    s_res = s_ee - (s_en**2 / s_nn if s_nn > 0 else 0.0)
    t = np.asarray(tr.time_s, float)
    mean_t = np.bincount(pof[use], weights=t[use], minlength=P) / np.maximum(n, 1)
    u = np.round(np.mod(t[use] * tr.step_frequency - ev.step_phase, 1.0), 6) % 1.0
    phases, ui = np.unique(u, return_inverse=True)
    counts = np.zeros((P, len(phases)))
    np.add.at(counts, (pof[use], ui), 1.0)
    return RunData(
        kind="events", plateau_n=n, plateau_mean_e=mean_e, plateau_mean_steps=mean_s,
        plateau_level0=level0, plateau_mean_t=mean_t, frame_phases=phases, phase_counts=counts, s_nn=s_nn,
        slope_hat=slope,
        s_res=max(s_res, 0.0), trigger_steps=np.asarray(triggers, int), **drop, **base,
    )


