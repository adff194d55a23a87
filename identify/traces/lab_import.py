"""Lab recordings into traces: the load point's velocity steps found in its displacement,
friction turned into spring elongation through the stated stiffness and normal load.

A friction lab records friction μ (shear over normal stress) and the load point's
displacement; its stiffness is stated in friction per µm of load-point displacement
(k/Nb). A trace stores elongation e = μ·Nb/k, so any consistent (k, Nb) pair gives the
same μ back: the normal load only sets the trace's units, and is recorded as stated.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from identify.model.rsf import VelocityDrive
from identify.traces.io import Trace
from identify.traces.look import LookFile

__all__ = ["detect_velocity_steps", "import_run", "ImportedRun"]

_SAME_VELOCITY = np.log(1.25)  # blocks whose velocities differ by less than 25 % are one stretch
_BLOCK = 40  # samples per block of the velocity scan (a rate change keeps blocks short in time)


def _block_velocities(t: np.ndarray, x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start index, least-squares velocity, its standard error) of consecutive blocks of
    ``n`` samples."""
    starts = np.arange(0, len(t) - n + 1, n)
    v, se = np.empty(len(starts)), np.empty(len(starts))
    for j, i in enumerate(starts):
        tt, xx = t[i:i + n], x[i:i + n]
        tc = tt - tt.mean()
        v[j] = float(tc @ (xx - xx.mean()) / (tc @ tc))
        r = xx - xx.mean() - v[j] * tc
        se[j] = float(np.sqrt(r @ r / (n - 2) / (tc @ tc)))
    return starts, v, se


def _two_line_rss(t: np.ndarray, x: np.ndarray, tc: float) -> float:
    """Residual sum of squares of the continuous two-line fit to (t, x) bending at ``tc``."""
    X = np.column_stack([np.ones_like(t), np.minimum(t - tc, 0), np.maximum(t - tc, 0)])
    c, *_ = np.linalg.lstsq(X, x, rcond=None)
    return float(np.sum((X @ c - x) ** 2))


def _refine_change(t: np.ndarray, x: np.ndarray, near: slice) -> float:
    """The time at which a continuous two-line fit to the two stretches (t, x) bends best:
    the best sample in ``near`` (the blocks around the change), then between its
    neighbours on every sample of both stretches. On the sample grid a change is off by up
    to half a sample, a few per cent of a transient's time scale at a lab's 100 Hz
    (measured on p655: 9 ms before the sample, the misfit 2.30 -> 2.22 of the steady
    scatter); the blocks alone place it by a noisy 0.8 s of data."""
    from scipy.optimize import minimize_scalar

    tn = t[near]
    rss = [_two_line_rss(t, x, tc) for tc in tn[2:-2]]
    k = int(np.argmin(rss)) + 2
    fine = minimize_scalar(lambda tc: _two_line_rss(t, x, tc), bounds=(float(tn[k - 1]), float(tn[k + 1])),
                           method="bounded", options={"xatol": 1e-4 * float(tn[k + 1] - tn[k - 1])})
    return float(fine.x) if fine.success and fine.fun <= rss[k - 2] else float(tn[k])


def detect_velocity_steps(time_s: np.ndarray, displacement_um: np.ndarray, *, hold_fraction: float = 0.01,
                          block: int = _BLOCK) -> tuple[VelocityDrive, list[float]]:
    """The load point's stretches of constant velocity in a recorded displacement:
    (drive with the measured velocities, µm/s; each stretch's slope standard error).

    Blocks of ``block`` samples get a least-squares velocity; neighbouring blocks within
    25 % of each other (or both holds: not distinguishable from zero, or below
    ``hold_fraction`` of the median block velocity) form one stretch; each change is placed
    where a continuous two-line fit across it bends.
    """
    t, x = np.asarray(time_s, float), np.asarray(displacement_um, float)
    if t.size < 3 * block:
        raise ValueError(f"{t.size} samples: too few to find velocity steps (at least {3 * block})")
    starts, v, se = _block_velocities(t, x, block)
    # a hold: a block whose velocity is not distinguishable from zero (the displacement's
    # quantisation and noise set how slow that is), or below hold_fraction of the median
    hold = np.abs(v) < np.maximum(3 * se, hold_fraction * float(np.median(np.abs(v))))
    v = np.where(hold, 0.0, v)

    def same(a, b):
        if a == 0 or b == 0:
            return a == b
        if a < 0 or b < 0:
            return False
        return abs(np.log(a / b)) < _SAME_VELOCITY

    groups = [[0]]
    for j in range(1, len(v)):
        if same(float(np.median(v[groups[-1]])), v[j]):
            groups[-1].append(j)
        else:
            groups.append([j])
    # a lone block between two stretches straddles the change: it joins neither
    last = len(groups) - 1
    kept = []
    for i, g in enumerate(groups):
        if len(g) < 2 and i not in (0, last):
            continue
        if kept and same(float(np.median(v[kept[-1]])), float(np.median(v[g]))):
            kept[-1] = kept[-1] + g  # (the two sides of a dropped block)
        else:
            kept.append(g)
    groups = kept
    times, edges = [float(t[0])], []
    for g0, g1 in zip(groups, groups[1:]):
        a, b = starts[g0[0]], min(starts[g1[-1]] + block, len(t))  # the two stretches
        i0, i1 = starts[g0[-1]], min(starts[g1[0]] + block, len(t))  # the blocks around the change
        edges.append(_refine_change(t[a:b], x[a:b], slice(i0 - a, i1 - a)))
    times += edges
    while True:
        vels, ses = _stretch_velocities(t, x, times)
        # (neighbours that the blocks split but whose whole stretches agree are one)
        joint = [i for i in range(1, len(times)) if same(vels[i - 1], vels[i])]
        if not joint:
            break
        del times[joint[0]]
    return VelocityDrive(tuple(times), tuple(vels)), ses


def _stretch_velocities(t: np.ndarray, x: np.ndarray, times: list) -> tuple[list, list]:
    """Each stretch's least-squares velocity (0 when not distinguishable from zero, a
    hold) and its standard error."""
    bounds = list(times) + [float(t[-1]) + 1.0]
    vels, ses = [], []
    for a, b in zip(bounds, bounds[1:]):
        m = (t >= a) & (t < b)
        tc = t[m] - t[m].mean()
        slope = float(tc @ (x[m] - x[m].mean()) / (tc @ tc))
        resid = x[m] - x[m].mean() - slope * tc
        ses.append(float(np.sqrt(resid @ resid / max(m.sum() - 2, 1) / (tc @ tc))))
        vels.append(0.0 if abs(slope) < 3 * ses[-1] else max(slope, 0.0))
    return vels, ses


@dataclass
class ImportedRun:
    """A run made from a lab recording: the ``trace`` and the ``assumptions`` made on the
    way (one sentence each, for the user to read)."""

    trace: Trace
    assumptions: list


def import_run(look: LookFile, *, friction: str | int, time: str | int, load_point: str | int | None,
               stiffness_per_um: float, normal_load_uN: float | None = None,
               window_s: tuple[float, float] | None = None, velocities_um_per_s: Sequence[float] | None = None,
               name: str | None = None, notes: str = "") -> ImportedRun:
    """A trace of one stretch of a lab recording (columns named or numbered from 0; no
    ``load_point`` column: the drive is the one velocity given).

    ``stiffness_per_um``: the loading system's stiffness in friction per µm of load-point
    displacement. ``normal_load_uN``: the normal load as stated (default 1 N: only k/Nb
    enters a fit). ``window_s``: the stretch to keep. ``velocities_um_per_s``: the nominal
    velocities of the stretches found (as the lab states them), in place of the measured
    ones; their number must match."""
    if not (stiffness_per_um > 0 and np.isfinite(stiffness_per_um)):
        raise ValueError(f"stiffness_per_um = {stiffness_per_um!r}: must be a finite number > 0 (friction per µm)")
    said = []
    if normal_load_uN is None:
        normal_load_uN = 1e6
        said.append("normal load not given: recorded as 1 N (only k/Nb enters a fit)")
    if load_point is None and (velocities_um_per_s is None or len(velocities_um_per_s) != 1):
        raise ValueError("without a load-point column the drive is one constant velocity: give exactly one "
                         "velocity (velocities_um_per_s=[V], --velocities V)")
    t, mu = (np.asarray(look[c].values, float) for c in (time, friction))
    lp = np.asarray(look[load_point].values, float) if load_point is not None else np.zeros_like(t)
    keep = np.isfinite(t) & np.isfinite(mu) & np.isfinite(lp)
    if window_s is not None:
        keep &= (t >= window_s[0]) & (t <= window_s[1])
    if keep.sum() < 10:
        raise ValueError(f"{look.path}: {keep.sum()} usable samples in the window {window_s}")
    t, mu, lp = t[keep], mu[keep], lp[keep]
    if load_point is None:
        drive = VelocityDrive((float(t[0]),), (float(velocities_um_per_s[0]),))
        said.append(f"load point not recorded: driven at {velocities_um_per_s[0]:g} µm/s throughout, as given")
    else:
        drive, ses = detect_velocity_steps(t, lp)
        measured = ", ".join(f"{v:.4g} ± {s:.2g}" for v, s in zip(drive.velocities_um_per_s, ses))
        said.append(f"load point: {len(drive.times_s)} stretch(es) found in {look[load_point].name!r}, at "
                    + ", ".join(f"{x:.6g} s" for x in drive.times_s) + f"; measured velocities {measured} µm/s")
    if velocities_um_per_s is not None and load_point is not None:
        if len(velocities_um_per_s) != len(drive.velocities_um_per_s):
            raise ValueError(f"{len(velocities_um_per_s)} velocities given for the {len(drive.times_s)} stretch(es) "
                             f"found (measured {measured} µm/s)")
        drive = VelocityDrive(drive.times_s, tuple(float(v) for v in velocities_um_per_s))
        said.append("velocities taken as given (nominal): " + ", ".join(f"{v:g}" for v in velocities_um_per_s)
                    + " µm/s")
    k_N_per_m = stiffness_per_um * normal_load_uN  # (1 N/m = 1 µN/µm)
    said.append(f"friction to elongation: e = μ / ({stiffness_per_um:g} per µm); spring constant "
                f"{k_N_per_m:.6g} N/m at the normal load {normal_load_uN:.6g} µN")
    meta = {"format": "nanofrictor-trace/1", "spring_constant_N_per_m": float(k_N_per_m),
            "normal_load_uN": float(normal_load_uN), "drive": drive.to_dict(), "outside_platform_ranges": True,
            "notes": notes or f"imported from {Path(look.path).name if look.path else look.title}",
            "imported": {"source": Path(look.path).name if look.path else look.title, "friction": look[friction].name,
                         "time": look[time].name,
                         "load_point": look[load_point].name if load_point is not None else None,
                         "stiffness_per_um": float(stiffness_per_um), "assumptions": said}}
    trace = Trace(name=name or (look.title or "run"), time_s=t, elongation=mu / stiffness_per_um * 1e-6,
                  puller=lp * 1e-6 if load_point is not None else None, metadata=meta)
    return ImportedRun(trace, said)
