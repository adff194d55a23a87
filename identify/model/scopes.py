"""Parameters that take one value per run or per device (``drift_rate@run:NAME``,
``k_scale@device:LABEL``).

A lab's gap rarely acts the same on every run: a camera drifts at its own rate in each
run, and spring constants are calibrated per spring, so one device may be off while the
others are right. A *scoped* parameter is a model or measurement parameter of
:data:`SCOPABLE` with a scope: for the runs inside the scope it replaces the global value,
everywhere the global value enters (the simulator, the NLP, the reports). Scoped names
are written ``base@run:NAME`` (the run's trace name) or ``base@device:LABEL``; a run's
device is its trace's ``device`` field, else its nominal spring constant (``k2.13`` for
2.13 N/m: springs are what the toolkit's devices differ by). A run-scoped value wins over
a device-scoped one, which wins over the global value.

The names go wherever a parameter name goes (``FitOptions.free``, ``fixed``, ``bounds``,
the result's parameters and JSON), with the base parameter's unit, bounds and scale.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

__all__ = ["SCOPABLE", "SCOPES", "scoped", "parse", "is_scoped", "label", "device_label", "resolve",
           "device_of", "run_scope_value"]

# (the walk's modes written out: identify.model.params reads this module, so it cannot be
# read from here; a test checks they are params.walk_names())
SCOPABLE = ("drift_rate", "k_scale", "load_offset", "load_scale", "clock_shift") + tuple(
    f"walk_{m}" for m in range(1, 7))
"""Parameters that may carry a scope: what differs between a lab's runs (drift and the
camera's random walk, the camera's clock against the puller's) or devices (spring
calibration, adhesion, load calibration)."""
SCOPES = ("run", "device")


def scoped(base: str, scope: str, label: str) -> str:
    """The name of ``base`` for one run or device: ``scoped("drift_rate", "run", "r1")``
    is ``"drift_rate@run:r1"``."""
    if base not in SCOPABLE:
        raise ValueError(f"{base!r} cannot take a per-{scope} value; these can: {', '.join(SCOPABLE)}")
    if scope not in SCOPES:
        raise ValueError(f"scope {scope!r}: choose 'run' or 'device'")
    label = str(label)
    if not label or "," in label or "@" in label:
        raise ValueError(f"{scope} label {label!r}: must be non-empty, without ',' or '@'")
    return f"{base}@{scope}:{label}"


def is_scoped(name: str) -> bool:
    return "@" in name


def parse(name: str) -> tuple[str, str | None, str | None]:
    """(base, scope, label) of a name; (name, None, None) for a global one; label None
    for ``base@run`` or ``base@device``, which a fit writes out for every run or device.
    A malformed scoped name raises ``ValueError`` naming the rule it broke."""
    if "@" not in name:
        return name, None, None
    base, _, rest = name.partition("@")
    scope, sep, label = rest.partition(":")
    if base not in SCOPABLE:
        raise ValueError(f"{name!r}: {base!r} cannot take a per-run or per-device value; "
                         f"these can: {', '.join(SCOPABLE)}")
    if scope not in SCOPES or (sep and not label):
        raise ValueError(f"{name!r}: write a scoped parameter as {base}@run:NAME or {base}@device:LABEL "
                         f"({base}@run or {base}@device: one for every run or device)")
    return base, scope, label or None


def label(name: str) -> str:
    """A run's or device's name as a scope label: ',' and '@' (which a list of names and a
    scoped name use) read as '_'."""
    return str(name).replace(",", "_").replace("@", "_")


def device_label(device: str | None, spring_constant: float) -> str:
    """A run's device: its trace's ``device`` field, else its nominal spring constant
    (``k2.13``)."""
    if device:
        return label(device)
    return f"k{spring_constant:g}"


def device_of(run) -> str:
    """The device of a run (anything with ``k`` and perhaps ``device``, as a fit's run
    data): its ``device`` if it has one, else its spring constant's label."""
    return getattr(run, "device", "") or device_label(None, run.k)


def run_scope_value(values: Mapping, base: str, run: str, device: str):
    """The value ``base`` takes in one run: run-scoped, else device-scoped, else global
    (works for numbers and CasADi symbols alike)."""
    for key in (f"{base}@run:{label(run)}", f"{base}@device:{device}"):
        if key in values:
            return values[key]
    return values[base]


def resolve(values: Mapping, run: str, device: str) -> dict:
    """``values`` as one run sees them: each base parameter set to its value in the run,
    the scoped names dropped (for the simulator, which knows no scopes)."""
    out = {k: v for k, v in values.items() if not is_scoped(k)}
    for base in {parse(k)[0] for k in values if is_scoped(k)}:
        try:
            out[base] = run_scope_value(values, base, run, device)
        except KeyError:  # no value of its own here and none global: the caller's default
            pass
    return out


def scoped_spec(name: str, base_spec):
    """The spec of a scoped name: its base's, renamed, the scope in its description."""
    base, scope, label = parse(name)
    where = f"{scope} {label}" if label else f"each {scope}"
    return dataclasses.replace(base_spec, name=name, description=f"{base_spec.description} ({where})")
