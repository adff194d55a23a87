"""A fit's options made concrete for its runs: ``base@run`` and ``base@device`` in
``free``, ``bounds`` and ``priors`` written out for every run or device, the walk's
Wiener priors set from each run's span, and the scoped names checked against the runs
(:mod:`identify.model.scopes`).

The user names a per-run parameter once (``drift_rate@run``); which runs it means is known
only once the traces are read and the runs that cannot be fitted are left out.
"""

from __future__ import annotations

from identify.fitting.options import FitError, FitOptions
from identify.model.params import walk_mode, walk_prior_sd
from identify.model.scopes import device_of, is_scoped, label, parse

__all__ = ["RATIO_ONLY", "every_scope", "check_scopes", "scoped_defaults"]

RATIO_ONLY = ("k_scale", "load_scale")
"""Factors a common value of which the friction coefficients absorb: per device, one
device is the reference (the one with the most runs) and keeps the null."""


def scoped_defaults(preset: dict, opts: FitOptions) -> dict:
    """The preset with a value for every per-run or per-device parameter the options name
    (:mod:`identify.model.scopes`): its base parameter's, unless fixed or started."""
    out = dict(preset)
    for name in (*opts.free, *opts.start):
        if is_scoped(name) and name not in out:
            out[name] = out[parse(name)[0]]
    return out


def every_scope(opts: FitOptions, run_data) -> FitOptions:
    """The options with ``base@run`` and ``base@device`` (no label) in ``free``, ``bounds``
    and ``priors`` written out: one parameter per run fitted by its frames (a creeping
    run's steady level shows no drift), or per device of the runs; for a factor
    (:data:`RATIO_ONLY`) every device but the one with the most runs, as the diagnosis's
    candidates do. Then each free walk coefficient without a prior gets the Wiener
    prior of ``walk_intensity`` over its run's span, where that is set."""
    wide = [n for n in opts.free if is_scoped(n) and parse(n)[2] is None]
    if not wide:
        return _walk_priors(opts, run_data)
    runs = [label(r.name) for r in run_data if r.kind == "events"]
    devices = list(dict.fromkeys(device_of(r) for r in run_data))
    out, bounds, priors = [], dict(opts.bounds), dict(opts.priors)
    for n in opts.free:
        base, scope, lab = parse(n) if is_scoped(n) else (n, None, None)
        if scope is None or lab is not None:
            out.append(n)
            continue
        labels = runs if scope == "run" else devices
        if base in RATIO_ONLY and len(labels) > 1:
            dev = [device_of(r) for r in run_data]
            labels = [d for d in labels if d != max(sorted(labels), key=dev.count)]
        names = [f"{base}@{scope}:{lab}" for lab in labels]
        out += [m for m in names if m not in out]
        for given in (bounds, priors):
            if n in given:
                value = given.pop(n)
                given.update({m: value for m in names if m not in given})
    return _walk_priors(opts.evolve(free=tuple(out), bounds=bounds, priors=priors), run_data)


def _walk_priors(opts: FitOptions, run_data) -> FitOptions:
    """``opts`` with the Wiener prior on each free run-scoped walk coefficient that has
    none of its own, at ``opts.walk_intensity`` (unchanged where that is not set)."""
    if opts.walk_intensity is None:
        return opts
    if not any(walk_mode(n) for n in opts.free):
        raise FitError("walk_intensity: no walk coefficient is free, so there is no walk to put its prior on; "
                       "free walk_1@run ... walk_6@run (identify fit's --walk-nm-per-sqrt-s does)")
    spans = {label(r.name): float(r.span_s) for r in run_data}
    priors = dict(opts.priors)
    for n in opts.free:
        m = walk_mode(n)
        if m is None or n in priors or not is_scoped(n):
            continue
        base, scope, lab = parse(n)
        if scope != "run":
            raise FitError(f"free: {n}: a walk with walk_intensity is one run's (the prior needs the run's "
                           f"span); free {base}@run or {base}@run:NAME")
        if lab in spans:  # (a run not fitted: check_scopes names it)
            priors[n] = walk_prior_sd(opts.walk_intensity, m, spans[lab])
    return opts.evolve(priors=priors)


def check_scopes(opts: FitOptions, run_data, excluded) -> None:
    """A per-run or per-device parameter must name a run or device that is fitted
    (``excluded``: (name, why) of the runs left out, for the message)."""
    runs = {label(r.name): r for r in run_data}
    devices = {device_of(r) for r in run_data}
    gone = {label(n): why for n, why in excluded}
    for name in (*opts.free, *opts.fixed):
        if not is_scoped(name):
            continue
        base, scope, lab = parse(name)
        known = runs if scope == "run" else devices
        where = "free" if name in opts.free else "fixed"
        if lab not in known:
            why = f" (left out: {gone[lab]})" if lab in gone else ""
            raise FitError(f"{where}: {name} names no {scope} of the fitted data{why}; the {scope}s are "
                           f"{', '.join(sorted(known)) or 'none'}", excluded)
        if scope == "run" and base == "drift_rate" and runs[lab].kind != "events":
            raise FitError(f"{where}: {name} names a run fitted by its steady level, which a drift does not "
                           "move (no resolvable slips)", excluded)
