"""What a fit says of one parameter: its estimate (:class:`ParameterEstimate`) and its
profile likelihood (:class:`Profile`, computed by :mod:`identify.fitting.profile_likelihood`),
each with its JSON form.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identify.jsonio import SavedResult

__all__ = ["ParameterEstimate", "Profile", "number_from_json", "pair_from_json"]


def number_from_json(x) -> float:
    """A JSON number back to a float (strict JSON writes a non-finite one as null)."""
    return float("nan") if x is None else float(x)


def pair_from_json(x):
    """A JSON two-list back to the tuple it was (None stays None)."""
    return None if x is None else tuple(x)


@dataclass
class ParameterEstimate:
    """One parameter: value (SI) ± stderr, 95 % interval, whether it was free."""

    name: str
    value: float
    stderr: float | None
    ci95: tuple | None
    free: bool
    unit: str
    init: float | None = None
    flag: str | None = None
    true: float | None = None
    # the profile likelihood's 95 % interval, beside (never instead of) ``ci95``; a side
    # the profile never closes is None there (the parameter is undetermined that way)
    ci95_profile: tuple | None = None

    def to_json(self) -> dict:
        return dict(value=self.value, stderr=self.stderr,
                    ci95=list(self.ci95) if self.ci95 is not None else None,
                    ci95_profile=list(self.ci95_profile) if self.ci95_profile is not None else None,
                    free=self.free, unit=self.unit, init=self.init, flag=self.flag, true=self.true)

    @classmethod
    def from_json(cls, name: str, d: dict) -> ParameterEstimate:
        return cls(name=name, value=number_from_json(d["value"]), stderr=d.get("stderr"),
                   ci95=pair_from_json(d.get("ci95")), free=bool(d["free"]), unit=d.get("unit", "-"),
                   init=d.get("init"), flag=d.get("flag"), true=d.get("true"),
                   ci95_profile=pair_from_json(d.get("ci95_profile")))


@dataclass
class Profile(SavedResult):
    """Profile likelihood of one parameter: Δχ² against its value.

    ``values``, ``delta_chi2``: the points whose constrained fit converged (the only ones
    that count); ``failed``: the values where it did not. ``ci95``: (lower, upper), a
    side None where Δχ² never reaches the threshold (``open_below``, ``open_above``:
    the data do not bound the parameter that way over the range walked, ``reach``);
    None when both are open (``flat``)."""

    name: str
    values: np.ndarray
    delta_chi2: np.ndarray
    ci95: tuple | None
    flat: bool
    threshold: float
    open_below: bool = False
    open_above: bool = False
    failed: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reach: tuple | None = None  # the farthest converged values walked, (below, above)
    # (value, Δχ² < 0) where a constrained fit beat the fit itself: the fit's optimum is
    # a local one, and ci95 is the interval about this better point
    better: tuple | None = None

    @property
    def undetermined(self) -> str | None:
        """'above', 'below', 'both' or None: where the profile leaves the parameter open."""
        if self.open_below and self.open_above:
            return "both"
        return "above" if self.open_above else "below" if self.open_below else None

    def interval_text(self, fmt: str = ".4g") -> str:
        """The interval with its open sides written out, e.g. ``[0.89, open)``."""
        if self.ci95 is None:
            return "no 95% bound on either side"
        lo = "(open" if self.ci95[0] is None else f"[{self.ci95[0]:{fmt}}"
        hi = "open)" if self.ci95[1] is None else f"{self.ci95[1]:{fmt}}]"
        return f"{lo}, {hi}"

    def to_json(self) -> dict:
        return dict(name=self.name, values=self.values.tolist(), delta_chi2=self.delta_chi2.tolist(),
                    ci95=list(self.ci95) if self.ci95 else None, flat=self.flat, threshold=self.threshold,
                    undetermined=self.undetermined, failed=np.asarray(self.failed).tolist(),
                    better=list(self.better) if self.better else None,
                    reach=list(self.reach) if self.reach else None)

    @classmethod
    def from_json(cls, d: dict) -> Profile:
        und = d.get("undetermined")
        return cls(name=d["name"], values=np.array(d["values"], float), delta_chi2=np.array(d["delta_chi2"], float),
                   ci95=pair_from_json(d.get("ci95")), flat=bool(d["flat"]), threshold=float(d["threshold"]),
                   open_below=und in ("below", "both"), open_above=und in ("above", "both"),
                   failed=np.array(d.get("failed") or [], float), reach=pair_from_json(d.get("reach")),
                   better=pair_from_json(d.get("better")))

    @classmethod
    def from_dict(cls, d: dict) -> Profile:
        """A profile from :meth:`to_dict` (the result protocol's name for :meth:`from_json`)."""
        return cls.from_json(d)

    def report(self) -> str:
        """The profile as text: its 95 % interval, the points it rests on and what it leaves open."""
        lines = [f"Profile likelihood of {self.name}: 95% interval {self.interval_text()} "
                 f"(Δχ² threshold {self.threshold:.3g}; {len(self.values)} converged point(s)"
                 + (f", {len(self.failed)} not converged" if len(self.failed) else "") + ")"]
        if self.undetermined:
            lines.append(f"    undetermined {self.undetermined}: the data do not bound {self.name} that way"
                         + (f" over [{self.reach[0]:.4g}, {self.reach[1]:.4g}]" if self.reach else ""))
        if self.better:
            lines.append(f"    a constrained fit beat the fit at {self.better[0]:.4g} (Δχ² {self.better[1]:.3g}): "
                         "the fit's optimum is a local one")
        lines += [f"    {v:12.6g}  Δχ² {dc:10.4g}" for v, dc in zip(self.values, self.delta_chi2)]
        return "\n".join(lines)

    def plot(self, ax=None):
        from identify.plots.fit import plot_profile

        return plot_profile(self, ax=ax)
