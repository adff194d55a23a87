"""Parameters declared as lmfit users declare them: each with a value, whether it varies,
and its bounds; turned into the fit's options (free, fixed, start, bounds).

    params = identify.Parameters.preset("FOTAS")       # Table II, μmax μmin τ A free
    params["tau"].set(value=0.05, min=1e-3, max=1.0)    # start and bounds, SI
    params["v_stick"].set(value=1e-5, vary=False)      # the stick option, fixed
    result = identify.fit(["data/FOTAS"], params=params)
    params.add("drift_rate", 0.0, prior=5e-8)           # free, with a zero-mean prior of sd 5e-8 m/s

Values are SI, as everywhere inside the toolkit (the parameter table's units,
:data:`identify.SPECS`); every value and bound is checked against the table when it is
set, with an error naming the parameter and the rule.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

from identify.fitting.options import DEFAULT_FREE
from identify.model.params import ParameterError, parameter_set, spec

__all__ = ["Parameter", "Parameters"]


@dataclass
class Parameter:
    """One parameter: ``value`` (SI; a start when it varies, the value when it does not),
    ``vary``, the bounds ``min``/``max`` of its search (default: the parameter
    table's), and ``prior``: the standard deviation of a zero-mean Gaussian prior on it
    while it varies (:attr:`identify.fitting.options.FitOptions.priors`), or None."""

    name: str
    value: float
    vary: bool = False
    min: float | None = None
    max: float | None = None
    prior: float | None = None
    _set: bool = False  # (whether the user gave the value: only those enter the options)

    def set(self, value: float | None = None, vary: bool | None = None, min: float | None = None,
            max: float | None = None, prior: float | None = None) -> Parameter:
        """Change what is given (lmfit's ``Parameter.set``, and ``prior``); checked against
        the table."""
        s = spec(self.name)
        if prior is not None and not (isinstance(prior, (int, float)) and math.isfinite(prior) and prior > 0):
            raise ParameterError(f"{self.name}: prior = {prior!r} must be a standard deviation > 0, in {s.unit}")
        if value is not None:
            self.value = s.check(value, "")
            self._set = True
        if vary is not None:
            if not isinstance(vary, bool):
                raise ParameterError(f"{self.name}: vary = {vary!r} must be True or False")
            self.vary = vary
        lo = self.min if min is None else s.check(min, "min of ")
        hi = self.max if max is None else s.check(max, "max of ")
        if lo is not None and hi is not None and not lo < hi:
            raise ParameterError(f"{self.name}: min = {lo:g} must be below max = {hi:g}")
        self.min, self.max = lo, hi
        if prior is not None:
            self.prior = float(prior)
        return self

    def __str__(self) -> str:
        s = spec(self.name)
        bounds = f", bounds [{self.min if self.min is not None else s.lower:.4g}, " \
                 f"{self.max if self.max is not None else s.upper:.4g}]" if self.vary else ""
        prior = f", prior sd {self.prior:.4g} {s.unit}" if self.vary and self.prior is not None else ""
        return f"{self.name} = {self.value:.6g} {s.unit} ({'varies' if self.vary else 'fixed'}{bounds}{prior})"


class Parameters(Mapping[str, Parameter]):
    """The model's parameters by name (a mapping of :class:`Parameter`)."""

    def __init__(self, items: Iterable[Parameter] = (), coating: str | None = None):
        self._items = {p.name: p for p in items}
        self.coating = coating  # (the preset the values came from; the fit's default coating)

    @classmethod
    def preset(cls, coating: str = "FOTAS", vary: Iterable[str] = DEFAULT_FREE) -> Parameters:
        """Every parameter of the coating's Table II preset, those in ``vary`` varying."""
        values = parameter_set(coating)
        vary = tuple(vary)
        unknown = [n for n in vary if n not in values]
        if unknown:
            raise ParameterError(f"vary: {', '.join(unknown)} not among the preset's parameters "
                                 f"({', '.join(values)})")
        return cls((Parameter(n, float(v), n in vary) for n, v in values.items()), coating=coating)

    def add(self, name: str, value: float, vary: bool = True, min: float | None = None,
            max: float | None = None, prior: float | None = None) -> Parameter:
        """Add (or replace) a parameter, e.g. an effect's (``load_offset``)."""
        p = Parameter(name, spec(name).check(value, ""), False)
        p.set(value=value, vary=vary, min=min, max=max, prior=prior)
        self._items[name] = p
        return p

    def __getitem__(self, name: str) -> Parameter:
        try:
            return self._items[name]
        except KeyError:
            raise KeyError(f"no parameter {name!r}; these are {', '.join(self._items)}") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __str__(self) -> str:
        width = max((len(n) for n in self._items), default=0)
        return "\n".join(str(p).replace(f"{n} =", f"{n:{width}s} =", 1) for n, p in self._items.items())

    def options(self) -> dict:
        """The fit's options these declare: ``free`` (those that vary), ``start`` (their
        values given by ``set`` or ``add``), ``bounds`` (theirs, where given, the table's
        otherwise) and ``fixed`` (the values given to those that do not vary; the rest keep
        the coating's preset); ``priors`` where a varying one has a prior."""
        free = tuple(n for n, p in self._items.items() if p.vary)
        if not free:
            raise ParameterError("no parameter varies: set vary=True on at least one")
        start = {n: p.value for n, p in self._items.items() if p.vary and p._set}
        fixed = {n: p.value for n, p in self._items.items() if not p.vary and p._set}
        bounds = {}
        for n in free:
            p, s = self._items[n], spec(n)
            if p.min is not None or p.max is not None:
                bounds[n] = (p.min if p.min is not None else s.lower, p.max if p.max is not None else s.upper)
        priors = {n: self._items[n].prior for n in free if self._items[n].prior is not None}
        return dict(free=free, start=start, fixed=fixed, bounds=bounds, **({"priors": priors} if priors else {}))


def merged_options(options, params: Mapping | None):
    """``options`` (a FitOptions or None) with what ``params`` declares: free, start,
    fixed and bounds come from the parameters, and the priors where any parameter has
    one; the other options stay."""
    from dataclasses import replace

    from identify.fitting.options import FitOptions

    options = options or FitOptions()
    if params is None:
        return options
    if not isinstance(params, Parameters):
        raise TypeError(f"params must be identify.Parameters, not {type(params).__name__}")
    return replace(options, **params.options())
