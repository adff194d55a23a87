"""Data sets with one effect switched on, for checking the diagnosis on data whose effect
the baseline does not have (tests, ``tests/bench/bench_diagnosis.py``).

The runs are those of the bundled data (``data/README.md``) — two springs, loads 5–60 µN,
step frequencies 10–1000 Hz, rests from near τ to saturated, a creep run — at 90 nm of
noise and two frames per step, with the simulator's stick option (v_stick = 1e-5 m/s,
which the baseline then fixes). ``effect=None`` gives the baseline model itself;
``effect="outside"`` an effect outside the library: every run's true normal load off its
nominal value by its own random error (±15 %), which no single global parameter mimics.
``"random_walk"``, alone or beside library effects, is another: each run's camera zero
wanders as a random walk (:data:`RANDOM_WALK_NM`), a thermal wander that only the
``drift_walk`` candidate models; ``drift_walk`` itself gives each run its own drift rate
(as ``drift_per_run``) with that walk besides.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from identify.model.effects import get_effect
from identify.model.params import parameter_set
from identify.model.scopes import device_label

__all__ = ["CONDITIONS", "QUICK_CONDITIONS", "withheld_dataset", "run_name"]

STICK = 1e-5
RANDOM_WALK_NM = 20.0
"""The random walk's default size, nm/√s: over the longest withheld run (~22 s) it wanders
by ~90 nm, the frames' noise."""

# (k N/m, Nb µN, fp Hz, travel µm): eight of the bundled conditions, except that the
# (2.13 N/m, 20 µN, 300 Hz) run is pulled at 100 Hz here. At 300 Hz the puller (13.8
# µm/s) is faster than the stick threshold (10 µm/s), where whether a slip ends jumps
# with the parameters (RunData.stick_edge); measured on the drift set (5e-8 m/s,
# drift the only candidate, 2026-11-23): with that run the drift refit hit its
# iteration limit and the verdict was `unexplained` (all candidates: the same); at
# 100 Hz drift was named, drift_rate 4.983e-8 ± 0.017e-8 m/s, held-out gap 0.273 ->
# 0.027 µm, `adequate`. These sets test the diagnosis, not that discontinuity.
CONDITIONS = (
    (2.13, 5.0, 100.0, 30.0),
    (2.13, 5.0, 30.0, 30.0),
    (2.13, 10.0, 100.0, 30.0),
    (2.13, 20.0, 100.0, 30.0),  # the bundled set's 300 Hz run: see the note above
    (2.13, 30.0, 10.0, 33.8),
    (20.3, 30.0, 100.0, 30.0),
    (20.3, 30.0, 30.0, 30.0),
    (20.3, 60.0, 100.0, 30.0),
)
QUICK_CONDITIONS = tuple((k, nb, fp, min(tr, 15.0)) for k, nb, fp, tr in CONDITIONS)


def withheld_dataset(effect: str | Sequence[str] | None, magnitude: float | Sequence | None = None, *,
                     coating: str = "FOTAS", seed: int = 0, noise_nm: float = 90.0,
                     conditions: Sequence = CONDITIONS, base: dict | None = None,
                     drift_walk_nm_per_sqrt_s: float = 0.0, frames_per_step: float = 2.0,
                     exposure_align: float | str = "centre") -> list:
    """Traces of ``conditions`` simulated with ``effect`` on (seeded noise per run).

    Parameters
    ----------
    effect : str, sequence of str, or None
        An id of :data:`identify.model.effects.EFFECTS`, ``"outside"``, or None (no effect); or
        several ids, every one of them on at once (forward selection must name each).
    magnitude : float or sequence, optional
        Value of the effect's parameter (default: its realistic magnitude); with several
        effects, one value (or None) per effect.
    base : dict, optional
        Parameter overrides of the truth (e.g. ``{"A": 0.015}``).
    drift_walk_nm_per_sqrt_s : float
        A random walk of each run's camera zero besides (nm/√s; a thermal wander no
        candidate models).
    frames_per_step : float
        The camera's frame rate over the step frequency: 2 puts the frames at a quarter
        and three quarters of each step interval; a rate not locked to the steps (5.3)
        puts frames at every phase, some just after the step at which a slip happens.
    exposure_align : str or float
        Where a blurred exposure sits on the timestamp ("start", "centre", "end").

    A per-run or per-device effect (``drift_per_run``, ``spring_constant_per_device``,
    ``load_offset_per_device``) takes its values run by run from
    :meth:`identify.model.effects.Effect.run_values`; the runs are named as the fit
    names them and their device is their spring constant (``k2.13``).
    """
    from identify.simulation.hybrid import simulate

    truth = dict(parameter_set(coating))
    truth.update(v_stick=STICK, exposure_align=exposure_align)
    truth.update(base or {})
    law = "exponential"
    load_err = np.ones(len(conditions))
    ids, mags = _effects_and_magnitudes(effect, magnitude)
    if "random_walk" in ids:
        mag = mags.pop(ids.index("random_walk"))
        ids.remove("random_walk")
        drift_walk_nm_per_sqrt_s += RANDOM_WALK_NM if mag is None else float(mag)
    if "drift_walk" in ids:  # its rates as drift_per_run's, and the walk it is named for
        drift_walk_nm_per_sqrt_s += RANDOM_WALK_NM
    if ids == ["outside"]:
        rng = np.random.default_rng(10_000 + seed)
        load_err = 1 + rng.uniform(-0.15, 0.15, len(conditions))
    names = [run_name(c) for c in conditions]
    per_run = [{} for _ in conditions]
    for eid, mag in zip(ids, mags):
        if eid == "outside":
            continue
        eff = get_effect(eid)
        if eff.law is not None:
            law = eff.law
        if eff.scope is not None:
            devices = [device_label(None, c[0]) for c in conditions]
            for own, vals in zip(per_run, eff.run_values(list(zip(names, devices)), mag, seed)):
                own.update(vals)
        else:
            truth.update(eff.simulation_values(mag, truth))
    traces = []
    for i, (k, nb, fp, travel) in enumerate(conditions):
        params = {**truth, **per_run[i]}
        camera = {n: params.pop(n) for n in ("exposure", "exposure_align", "drift_rate", "e_offset") if n in params}
        run = simulate(coating, spring_constant_N_per_m=k, normal_load_uN=nb * load_err[i], step_frequency_Hz=fp,
                       travel_um=travel, law=law, params=params, stick_speed_m_per_s=params.get("v_stick"))
        tr = run.sample(noise_nm=noise_nm, seed=1000 * seed + i, name=names[i], frame_rate_Hz=frames_per_step * fp,
                        exposure_s=camera.get("exposure", 0.0),
                        exposure_align=camera.get("exposure_align", 0.5),
                        drift_rate_m_per_s=camera.get("drift_rate", 0.0),
                        offset_m=camera.get("e_offset", 0.0),
                        drift_walk_m_per_sqrt_s=drift_walk_nm_per_sqrt_s * 1e-9)
        if ids == ["outside"]:
            tr = _with_nominal_load(tr, nb * 1e-6)
        traces.append(tr)
    return traces


def run_name(condition) -> str:
    """A withheld set's run name for ``(k N/m, Nb µN, fp Hz, travel µm)``."""
    k, nb, fp = condition[:3]
    return f"k{k:g}_Nb{nb:g}uN_fp{fp:g}Hz"


def _effects_and_magnitudes(effect, magnitude) -> tuple[list, list]:
    """The effect ids and their magnitudes, checked: ("outside" alone; at most one aging law;
    no effect twice; one magnitude per effect)."""
    if effect is None:
        return [], []
    if isinstance(effect, str):
        return [effect], [magnitude]
    ids = list(effect)
    mags = [None] * len(ids) if magnitude is None else list(np.atleast_1d(np.asarray(magnitude, dtype=object)))
    if len(mags) != len(ids):
        raise ValueError(f"magnitude: {len(mags)} value(s) for {len(ids)} effects {ids}; give one per effect "
                         "(None for the realistic magnitude)")
    if len(set(ids)) != len(ids):
        raise ValueError(f"effect: {ids} names an effect twice")
    if "outside" in ids and len(ids) > 1:
        raise ValueError("effect: 'outside' is a data set of its own and cannot be combined with library effects")
    laws = [e for e in ids if e not in ("outside", "random_walk") and get_effect(e).law is not None]
    if len(laws) > 1:
        raise ValueError(f"effect: {laws} are aging laws; the data can follow only one")
    return ids, mags


def _with_nominal_load(trace, nominal_N: float):
    """The same frames with the metadata's normal load set to the nominal (wrong) value."""
    import dataclasses

    meta = dict(trace.metadata)
    meta.pop("block_voltage_V", None)
    meta["normal_load_uN"] = nominal_N * 1e6
    return dataclasses.replace(trace, metadata=meta)
