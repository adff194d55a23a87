"""Aging laws: how the state part ψ of the friction coefficient evolves.

Each law is written once, in a backend-neutral way: the same method builds the CasADi
expression of the hybrid model and evaluates NumPy arrays for the closed-form stick
phases and the reduced analysis. Pass ``ops=casadi`` for symbols, ``ops=numpy``
(default) for numbers.

The rate part of friction, ``A·ln(1 + |ẋ|/vc)`` (Eq. 18), is common to all laws.
The laws (paper, Sec. I and Sec. V; MODEL.md):

exponential (the paper's, Eqs. 10, 15, 19)
    dψ/dt = (μmax − ψ)/τ − (ψ − μmin)·|ẋ|/dc;  at rest ψ(t) = μmax − (μmax − ψ0)·e^(−t/τ) (Eq. 11)
logarithmic (Dieterich–Ruina, Eqs. 1–2)
    state φ (contact age, s): dφ/dt = 1 − |ẋ|·φ/dc;  ψ = μ0 + B·ln(1 + vc·φ/dc);
    at rest φ(t) = φ0 + t, so μs grows like ln(1 + t·vc/dc) without bound
logistic (Carlson–Batista phase-transition model, Eqs. 3–4, normalised by Nb)
    dψ/dt = |ψ − μmin|(μmax − ψ)/(τ·(μmax − μmin)) − (ψ − μmin)·|ẋ|/dc;
    at rest ψ(t) = μmin + Δ·q/(q + (1 − q)·e^(−t/τ)),  Δ = μmax − μmin, q = (ψ0 − μmin)/Δ
    (the melting coefficient α of Eq. 4 is 1/dc, and τ is scaled so it is a time in s).
    The law lives on μmin ≤ ψ; the absolute value extends it below μmin, where a state
    can be put by a fit (the contact state at a slip's trigger, from the data's elongation
    and the current parameters), so that such a state relaxes back up to μmin as the
    exponential law's would; the law as written diverges there instead, in ~τ (see
    :class:`Logistic`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["AgingLaw", "Exponential", "Logarithmic", "Logistic", "LAWS", "get_law"]


class AgingLaw:
    """Interface of an aging law (see the module docstring for the equations).

    Attributes
    ----------
    name : str
        Identifier used by the CLI (``--law``) and in results.
    parameters : tuple of str
        Names of the law's own parameters in :data:`identify.model.params.SPECS`.
    state_name, state_unit : str
        The law's state variable (ψ, dimensionless, for the exponential law).
    state_scale : float
        Typical magnitude of the state, for integrator scaling.
    """

    name: str = ""
    parameters: tuple[str, ...] = ()
    state_name: str = "psi"
    state_unit: str = "-"
    state_scale: float = 1.0

    # --- used by the hybrid model -------------------------------------------------
    def static_coefficient(self, state: Any, p: Mapping[str, Any], ops: Any = np) -> Any:
        """ψ: the state part of the friction coefficient (static capacity = ψ·Nb)."""
        raise NotImplementedError

    def rate(self, state: Any, speed: Any, p: Mapping[str, Any], ops: Any = np) -> Any:
        """d(state)/dt at sliding speed ``speed`` = |ẋ| (m/s)."""
        raise NotImplementedError

    def rest(self, state0: Any, t: Any, p: Mapping[str, Any], ops: Any = np) -> Any:
        """State after a rest of ``t`` seconds that started at ``state0`` (closed form)."""
        raise NotImplementedError

    def aged_state(self, p: Mapping[str, float]) -> float:
        """Default initial state: a fully aged contact."""
        raise NotImplementedError

    def state_from_coefficient(self, mu: Any, p: Mapping[str, Any], ops: Any = np) -> Any:
        """Inverse of :meth:`static_coefficient`: the state whose ψ is ``mu``."""
        return mu

    state_bounds: tuple[float, float] = (0.0, 3.0)
    """Admissible range of the state (for the identification's bounds)."""

    def rejuvenated_state(self, p: Mapping[str, float]) -> float:
        """The state just after a long slip (memory fully lost)."""
        raise NotImplementedError

    def steady_state(self, speed: Any, p: Mapping[str, Any], ops: Any = np) -> Any:
        """State of steady sliding at ``speed`` (m/s), where :meth:`rate` vanishes."""
        raise NotImplementedError

    # --- used by the reduced analysis (Eq. 9 and Figs. 10-11) -------------------------
    curve_parameters: tuple[str, ...] = ()

    def static_curve(self, t_rest: Any, theta: Any, ops: Any = np) -> Any:
        """μs after a rest ``t_rest`` from a rejuvenated contact, in the law's reduced
        parameters ``theta`` (ordered as :attr:`curve_parameters`)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<aging law {self.name!r}>"


def _rate_term(speed, p, ops=np):
    """Velocity strengthening A·ln(1 + |ẋ|/vc) of Eq. 18."""
    return p["A"] * ops.log(1 + speed / p["vc"])


@dataclass(frozen=True, repr=False)
class Exponential(AgingLaw):
    """The paper's exponential aging with slip rejuvenation (Eqs. 10, 11, 15, 19)."""

    name: str = "exponential"
    parameters: tuple[str, ...] = ("mu_max", "mu_min", "tau", "dc")
    curve_parameters: tuple[str, ...] = ("mu_max", "mu_min", "tau")

    def static_coefficient(self, state, p, ops=np):
        return state

    def rate(self, state, speed, p, ops=np):
        return (p["mu_max"] - state) / p["tau"] - (state - p["mu_min"]) * speed / p["dc"]

    def rest(self, state0, t, p, ops=np):
        return p["mu_max"] - (p["mu_max"] - state0) * ops.exp(-t / p["tau"])

    def aged_state(self, p):
        return float(p["mu_max"])

    def rejuvenated_state(self, p):
        return float(p["mu_min"])

    def steady_state(self, speed, p, ops=np):
        a = 1 / p["tau"]
        b = speed / p["dc"]
        return (a * p["mu_max"] + b * p["mu_min"]) / (a + b)

    def static_curve(self, t_rest, theta, ops=np):
        mu_max, mu_min, tau = theta[0], theta[1], theta[2]
        return mu_max - (mu_max - mu_min) * ops.exp(-t_rest / tau)


@dataclass(frozen=True, repr=False)
class Logarithmic(AgingLaw):
    """Dieterich–Ruina aging law, logarithmic and unbounded (Eqs. 1-2).

    The state is the contact age φ (s); the default initial contact has rested 1 s.
    """

    name: str = "logarithmic"
    parameters: tuple[str, ...] = ("mu_0", "B", "dc", "vc")
    state_name: str = "phi"
    state_unit: str = "s"
    state_scale: float = 1e-3
    initial_age_s: float = 1.0
    curve_parameters: tuple[str, ...] = ("mu_0", "B", "t_c")

    def static_coefficient(self, state, p, ops=np):
        return p["mu_0"] + p["B"] * ops.log(1 + p["vc"] * state / p["dc"])

    def state_from_coefficient(self, mu, p, ops=np):
        # (in numpy a coefficient far above μ0 overflows to an infinite age: that is the
        # answer, not a fault to warn of in every diagnosis's logarithmic-law candidate)
        with np.errstate(over="ignore"):
            return (ops.exp((mu - p["mu_0"]) / p["B"]) - 1) * p["dc"] / p["vc"]

    state_bounds: tuple[float, float] = (0.0, 1e6)

    def rate(self, state, speed, p, ops=np):
        return 1 - speed * state / p["dc"]

    def rest(self, state0, t, p, ops=np):
        return state0 + t

    def aged_state(self, p):
        return self.initial_age_s

    def rejuvenated_state(self, p):
        return 0.0

    def steady_state(self, speed, p, ops=np):
        return p["dc"] / speed

    def static_curve(self, t_rest, theta, ops=np):
        mu_0, b, t_c = theta[0], theta[1], theta[2]
        return mu_0 + b * ops.log(1 + t_rest / t_c)


_DECAY_FLOOR = 1e-30  # e^(−t/τ) below this: past 69 τ of rest (Logistic.rest)


@dataclass(frozen=True, repr=False)
class Logistic(AgingLaw):
    """Carlson–Batista phase-transition law, logistic and bounded (Eqs. 3-4).

    A fully rejuvenated contact (ψ = μmin exactly) never re-ages: the logistic law needs
    a seed of solid-like state, which is why it shows a nucleation delay.

    Below μmin the law as written is unstable: (ψ − μmin)(μmax − ψ) < 0 drives the state
    down, to −∞ in finite time at rest (the closed form has a pole at
    t = τ·ln((μmax − ψ0)/(μmin − ψ0))). A fit can start a slip there: the contact state at
    a trigger follows from the data's elongation, and a refit of the logistic law from an
    exponential baseline inherits states below its μmin (measured: on the withheld
    rejuvenation set at dc = 0.3 µm, one arc of a 20.3 N/m, 30 µN run started 0.014 below
    μmin with τ = 0.79 ms and could not be integrated at any tolerance, and the candidate
    "could not be evaluated at any start"). So the aging term uses |ψ − μmin|: below μmin
    the state relaxes back up to it, as under the exponential law, and never crosses it;
    on μmin ≤ ψ the law is unchanged. At rest below μmin, with a = μmin − ψ0,
    ψ(t) = μmin − Δ·a/((Δ + a)·e^(t/τ) − a).
    """

    name: str = "logistic"
    parameters: tuple[str, ...] = ("mu_max", "mu_min", "tau", "dc")
    curve_parameters: tuple[str, ...] = ("mu_max", "mu_min", "tau", "q0")

    def static_coefficient(self, state, p, ops=np):
        return state

    def rate(self, state, speed, p, ops=np):
        d = p["mu_max"] - p["mu_min"]
        u = state - p["mu_min"]
        return ops.fabs(u) * (p["mu_max"] - state) / (p["tau"] * d) - u * speed / p["dc"]

    def rest(self, state0, t, p, ops=np):
        lo, hi = p["mu_min"], p["mu_max"]
        d = hi - lo
        # each branch with its own clipped argument, so that the branch not taken stays
        # finite (no pole, no 0/0) and neither its value nor its derivative leaks; written
        # with e^(−t/τ) ≤ 1. Its floor moves no value by more than 1e-15 (tested): a seed ψ − μmin
        # is 0 or at least the state's round-off (~1e-16), re-aged fully by then; it keeps the
        # derivative at a fully rejuvenated contact, 1/e^(−t/τ), finite (measured: squared
        # in a held-out step's Gauss–Newton matrix it overflowed, and LAPACK was handed inf)
        decay = ops.fmax(ops.exp(-t / p["tau"]), _DECAY_FLOOR)
        up = ops.fmax(state0 - lo, 0.0)
        above = lo + d * up / (up + (d - up) * decay)
        down = ops.fmax(lo - state0, 0.0)
        below = lo - d * down * decay / (d + down - down * decay)
        if ops is np:
            return np.where(np.asarray(state0) >= lo, above, below)
        return ops.if_else(state0 >= lo, above, below)

    def aged_state(self, p):
        return float(p["mu_max"])

    def rejuvenated_state(self, p):
        return float(p["mu_min"])

    def steady_state(self, speed, p, ops=np):
        d = p["mu_max"] - p["mu_min"]
        s = p["mu_max"] - speed * p["tau"] * d / p["dc"]
        # below mu_min the only non-negative fixed point is mu_min itself
        return ops.fmax(s, p["mu_min"]) if hasattr(ops, "fmax") else np.maximum(s, p["mu_min"])

    def static_curve(self, t_rest, theta, ops=np):
        mu_max, mu_min, tau, q0 = theta[0], theta[1], theta[2], theta[3]
        return mu_min + (mu_max - mu_min) * q0 / (q0 + (1 - q0) * ops.exp(-t_rest / tau))


LAWS: dict[str, AgingLaw] = {law.name: law for law in (Exponential(), Logarithmic(), Logistic())}


def get_law(name: str | AgingLaw) -> AgingLaw:
    """The law called ``name``; a clear error lists the known ones."""
    if isinstance(name, AgingLaw):
        return name
    try:
        return LAWS[str(name).lower()]
    except KeyError:
        raise ValueError(
            f"law {name!r} is not known; choose one of {', '.join(LAWS)}"
        ) from None


def rate_term(speed, p, ops=np):
    """Public alias of the velocity-strengthening term A·ln(1 + |ẋ|/vc) (Eq. 18)."""
    return _rate_term(speed, p, ops)

