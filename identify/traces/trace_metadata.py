"""A run's conditions (the ``RUN.json`` content): the format's rules for them and the
order their keys are written in.

:func:`check_metadata` enforces every rule on the keys, :func:`key_line` points an error
at the line of the offending key, and :func:`ordered_metadata` gives the key order of
the written file.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NoReturn

from identify.model.params import ParameterError, normal_load_from_voltage
from identify.model.plausible import PLATFORM_RANGES, platform_problem
from identify.traces.trace_format import FORMAT, TraceFormatError

__all__ = ["check_metadata", "key_line", "ordered_metadata"]

# Key order of the JSON file: format first, then who/what, then conditions, then notes;
# keys not listed here follow in sorted order so the output never depends on how the
# dict was built.
_KEY_ORDER = (
    "format",
    "coating",
    "device",
    "spring_constant_N_per_m",
    "normal_load_uN",
    "block_voltage_V",
    "step_frequency_Hz",
    "drive",
    "step_size_nm",
    "frame_rate_Hz",
    "block_mass_kg",
    "notes",
)
_POSITIVE_REQUIRED = ("spring_constant_N_per_m",)
_POSITIVE_OPTIONAL = ("step_size_nm", "frame_rate_Hz", "block_mass_kg")
_TEXT_OPTIONAL = ("coating", "device", "notes")


def key_line(text: str | None, key: str) -> int | None:
    """Line of the first ``"key":`` in ``text`` (None if absent or no text)."""
    if text is None:
        return None
    m = re.search(r'"' + re.escape(key) + r'"\s*:', text)
    return None if m is None else text.count("\n", 0, m.start()) + 1


def _is_number(v: Any) -> bool:
    # bool is an int subclass; true/false are not numbers in this format
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def check_metadata(meta: Mapping[str, Any], path: str | Path, text: str | None = None) -> None:
    """Check the conditions of a run against the format; ``text`` locates lines."""

    def fail(key: str | None, rule: str) -> NoReturn:
        raise TraceFormatError(path, key_line(text, key) if key else None, rule)

    if "format" not in meta:
        fail(None, f"missing required key 'format' (must be {FORMAT!r})")
    if meta["format"] != FORMAT:
        fail("format", f"format must be {FORMAT!r}, found {meta['format']!r}")
    for key in _POSITIVE_REQUIRED:
        if key not in meta:
            fail(None, f"missing required key {key!r}")
    _check_drive(meta, fail)
    for key in _POSITIVE_REQUIRED + ("step_frequency_Hz",) + _POSITIVE_OPTIONAL:
        if key in meta:
            v = meta[key]
            if not _is_number(v) or not math.isfinite(v) or v <= 0:
                fail(key, f"{key} = {v!r}: must be a finite number > 0")
    has_load, has_voltage = "normal_load_uN" in meta, "block_voltage_V" in meta
    if has_load and has_voltage:
        fail("block_voltage_V", "give exactly one of normal_load_uN or block_voltage_V, not both")
    if not (has_load or has_voltage):
        fail(None, "missing the normal load: give exactly one of normal_load_uN or block_voltage_V")
    if has_load:
        v = meta["normal_load_uN"]
        if not _is_number(v) or not math.isfinite(v) or v <= 0:
            fail("normal_load_uN", f"normal_load_uN = {v!r}: must be a finite number > 0")
    else:
        v = meta["block_voltage_V"]
        if not _is_number(v) or not math.isfinite(v):
            fail("block_voltage_V", f"block_voltage_V = {v!r}: must be a finite number")
        try:
            normal_load_from_voltage(v)
        except ParameterError as exc:
            fail("block_voltage_V", str(exc))
    for key in _TEXT_OPTIONAL:
        v = meta.get(key)
        if v is not None and not isinstance(v, str):
            fail(key, f"{key} = {v!r}: must be text")
    outside = meta.get("outside_platform_ranges", False)
    if not isinstance(outside, bool):
        fail("outside_platform_ranges", f"outside_platform_ranges = {outside!r}: must be true or false")
    if not outside:
        for key in PLATFORM_RANGES:
            if key in meta and (problem := platform_problem(key, float(meta[key]))):
                fail(key, problem)


def _check_drive(meta: Mapping[str, Any], fail) -> None:
    """The puller: a stepper (``step_frequency_Hz``, the MEMS platform) or a continuous
    ``drive`` (a lab's load point), exactly one of them."""
    has_steps, drive = "step_frequency_Hz" in meta, meta.get("drive")
    if has_steps and drive is not None:
        fail("drive", "give step_frequency_Hz (a stepper) or drive (a continuous load point), not both")
    if not has_steps and drive is None:
        fail(None, "missing required key 'step_frequency_Hz' (or 'drive', for a load point that moves continuously)")
    if drive is None:
        return
    rule = ('drive must be {"kind": "velocity_steps", "times_s": [...], "velocities_um_per_s": [...]}: '
            "as many times as velocities (at least one), times increasing, velocities finite and >= 0")
    if not isinstance(drive, Mapping) or drive.get("kind") != "velocity_steps":
        fail("drive", rule)
    times, vels = drive.get("times_s"), drive.get("velocities_um_per_s")
    ok = (isinstance(times, list) and isinstance(vels, list) and len(times) == len(vels) >= 1
          and all(_is_number(x) and math.isfinite(x) for x in times + vels)
          and all(b > a for a, b in zip(times, times[1:])) and all(v >= 0 for v in vels))
    if not ok:
        fail("drive", f"{rule}; found {dict(drive)!r}")


def ordered_metadata(meta: Mapping[str, Any]) -> dict:
    """``meta`` with its keys in the written file's order (known keys first, the rest sorted)."""
    known = [k for k in _KEY_ORDER if k in meta]
    rest = sorted(k for k in meta if k not in _KEY_ORDER)
    return {k: meta[k] for k in known + rest}
