"""The hybrid stick/slip model of the nanofrictor, written once.

Physics (MODEL.md, Eqs. 18-20), with the model extensions of the diagnosis at their
null values (``identify.model.params`` kind ``effect``):

    spring force   F_s(e) = s_k·k·e·(1 + β·e²)                 (k_scale, beta)
    normal load    N      = s_N·Nb + F_a                        (load_scale, load_offset)
    friction       μ      = ψ(state) + μ_topo(x) + A·ln(1 + |ẋ|/vc)
    motion         mb·ẍ   = F_s(xp − x) − sgn(ẋ)·μ·N − (c + c_extra)·ẋ
    aging          d(state)/dt from the selected :mod:`identify.model.laws` law
    at rest        held while |F_s| ≤ (ψ + μ_topo)·N; the state ages in closed form
    stick option   v_stick > 0: a block slower than v_stick is held while
                   |F_s| ≤ (ψ + μ_topo + A·ln(1 + v_stick/vc))·N (a Karnopp band)

Every piece is a backend-neutral method (``ops=numpy`` for numbers, ``ops=casadi`` for
symbols), so the closed-form stick phases, the symbolic slip dynamics and the
identification all use the same expressions.

The symbolic slip model (:func:`slip_dae`) is time-scaled (the integrator runs over
[0, 1] and the duration is a parameter) and state-scaled (µm, mm/s, ms), so one
integrator Function serves every slip, and Ipopt and the integrators see numbers near 1.
States: x (µm), v (mm/s), state/state_scale, moving flag m, armed flag a (the stick
threshold arms once the block has been faster than it), the time spent frozen (ms),
the scaled state at the freezing instant (these two let a caller read the stop time and
state from any output after the stop) and the peak speed so far (mm/s, recorded by an
event where the acceleration changes sign). Control: xp (µm), piecewise
constant, one value per output interval (the puller's steps). A ``zero`` indicator
becomes negative when a sliding block stops (reverses) or, armed, falls below the stick
threshold; the ``transition`` freezes it (m = 0), after which only the state ages.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from identify.model.compiled import compiled
from identify.model.laws import AgingLaw, Exponential, get_law
from identify.model.params import SPECS, TOPO_MODES, topo_field_names

__all__ = [
    "Model",
    "LENGTH_UNIT",
    "SPEED_UNIT",
    "TIME_UNIT",
    "RUN_INPUTS",
    "slip_integrator",
    "slip_rhs",
    "STATE_INDEX",
    "N_STATES",
    "arc_dae",
    "transition",
]

LENGTH_UNIT = 1e-6  # m: positions in the integrator are in µm
SPEED_UNIT = 1e-3  # m/s: velocities in mm/s (= µm/ms)
TIME_UNIT = 1e-3  # s: integrator time in ms
STATE_INDEX = dict(x=0, v=1, state=2, moving=3, armed=4, frozen_ms=5, state_at_stop=6, peak_speed=7)
N_STATES = len(STATE_INDEX)
RUN_INPUTS = ("k", "Nb", "direction", "duration")
"""Per-call inputs appended to the model parameters: spring constant (N/m), normal load
(N), sliding direction (±1) and the integration horizon (ms)."""

# Effect and platform parameters every model carries (null values give the paper's model).
_PLATFORM = ("mb", "c", "step_size")
_EFFECTS = tuple(n for n, s in SPECS.items() if s.kind == "effect")


@dataclass(frozen=True)
class Model:
    """A friction model: an aging law with the paper's rate term and every extension.

    Parameters
    ----------
    law : AgingLaw or str
        ``exponential`` (the paper's, default), ``logarithmic`` or ``logistic``.
    """

    law: AgingLaw = field(default_factory=Exponential)

    def __post_init__(self):
        object.__setattr__(self, "law", get_law(self.law))

    # ------------------------------------------------------------------ names
    @property
    def friction_names(self) -> tuple[str, ...]:
        """Friction-law parameters: the law's own, then A and vc (Eq. 18)."""
        names = list(self.law.parameters)
        for n in ("A", "vc", "dc"):
            if n not in names:
                names.append(n)
        return tuple(names)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Every model parameter, in the order of the symbolic parameter vector."""
        return self.friction_names + _PLATFORM + _EFFECTS

    def defaults(self, values: Mapping[str, float]) -> dict[str, float]:
        """``values`` completed with spec nominals for anything missing."""
        return {n: float(values[n]) if n in values else SPECS[n].nominal for n in self.parameter_names}

    def pack(self, values: Mapping[str, float], k: float, Nb: float, direction: float = 1.0,
             duration_ms: float = 1.0) -> np.ndarray:
        """Numeric parameter vector of the slip DAE (model parameters, then RUN_INPUTS)."""
        v = self.defaults(values)
        return np.array([v[n] for n in self.parameter_names] + [k, Nb, direction, duration_ms])

    # ------------------------------------------------------------------ physics
    def spring_force(self, e, P, ops=np):
        """F_s(e) = s_k·k·e·(1 + β·e²), N (e in m)."""
        return P["k_scale"] * P["k"] * e * (1 + P["beta"] * e * e)

    def normal_load(self, P):
        """N = s_N·Nb + F_a, N."""
        return P["load_scale"] * P["Nb"] + P["load_offset"]

    def damping(self, P):
        """c + c_extra, N·s/m."""
        return P["c"] + P["c_extra"]

    def step(self, P):
        """True puller step, m."""
        return P["step_size"] * P["step_scale"]

    def topography(self, x, P, ops=np):
        """Friction coefficient's part that varies along the track: a ripple
        a·sin(2πx/λ + φ) plus a rough track Σⱼ cⱼ·cos(2πjx/L) + sⱼ·sin(2πjx/L)
        (:data:`identify.model.params.TOPO_MODES` modes)."""
        out = P["topo_amp"] * ops.sin(2 * np.pi * x / P["topo_wavelength"] + P["topo_phase"])
        coef = [P[n] for n in topo_field_names()]
        if all(isinstance(c, (int, float)) and c == 0 for c in coef):
            return out  # (the field off, as numbers: no terms to evaluate)
        th = 2 * np.pi * x / P["topo_length"]
        for j in range(1, TOPO_MODES + 1):
            out = out + P[f"topo_c{j}"] * ops.cos(j * th) + P[f"topo_s{j}"] * ops.sin(j * th)
        return out

    def static_coefficient(self, state, x, P, ops=np):
        """Static capacity per unit load at rest: ψ(state) + μ_topo(x)."""
        return self.law.static_coefficient(state, P, ops) + self.topography(x, P, ops)

    def hold_coefficient(self, state, x, P, ops=np):
        """Capacity per unit load of a block at rest.

        As written (v_stick = 0) it is the static part ψ + μ_topo. With the stick-threshold
        option it is the friction at the edge of the stick band, ψ + μ_topo +
        A·ln(1 + v_stick/vc): a Karnopp band in which a block slower than v_stick is held
        while the spring force stays within what friction can give at v_stick, so the
        capacity is continuous across the band edge.
        """
        return self.static_coefficient(state, x, P, ops) + P["A"] * ops.log(1 + P["v_stick"] / P["vc"])

    def friction_coefficient(self, state, speed, x, P, ops=np):
        """μ = ψ + μ_topo + A·ln(1 + |ẋ|/vc) (Eq. 18)."""
        return self.static_coefficient(state, x, P, ops) + P["A"] * ops.log(1 + speed / P["vc"])

    def holds(self, e, state, x, P, slack: float = 0.0):
        """Whether a block at rest stays put: |F_s(e)| ≤ capacity (NumPy, vectorised)."""
        cap = self.hold_coefficient(state, x, P) * self.normal_load(P)
        return np.abs(self.spring_force(e, P)) <= cap * (1 + slack)


@functools.cache
def _symbols(model: Model):
    names = model.parameter_names + RUN_INPUTS
    p = ca.SX.sym("p", len(names))
    P = {n: p[i] for i, n in enumerate(names)}
    X = ca.SX.sym("X", N_STATES)
    u = ca.SX.sym("xp_um")
    return names, p, P, X, u


@functools.cache
def slip_dae(model: Model) -> dict:
    """The symbolic slip-mode DAE (time- and state-scaled), with its zero indicators.

    Returns a dict with ``x``, ``u``, ``p``, ``ode``, ``zero`` (SX) and the names of
    the parameter vector under ``names``.
    """
    names, p, P, X, u = _symbols(model)
    law = model.law
    xi, eta, zeta, m, a = (X[i] for i in range(5))
    x = xi * LENGTH_UNIT
    v = eta * SPEED_UNIT
    state = zeta * law.state_scale
    e = u * LENGTH_UNIT - x
    s = P["direction"]
    speed = ca.fabs(v)
    N = model.normal_load(P)
    # The rate term is written as the odd function A·sgn(v)·ln(1 + |v|/vc): identical to
    # s·A·ln(1 + |v|/vc) while the block slides in direction s, C¹ through v = 0, and it
    # damps (rather than drives) the motion an integrator computes past a stop, so a
    # sub-interval that overshoots a stop stays cheap and finite.
    static = model.static_coefficient(state, x, P, ops=ca)
    rate = P["A"] * ca.sign(v) * ca.log1p(speed / P["vc"])
    force = model.spring_force(e, P, ops=ca) - (s * static + rate) * N - model.damping(P) * v
    T = P["duration"] * TIME_UNIT  # s, the horizon of this call
    moving = ca.vertcat(
        v / LENGTH_UNIT,
        force / P["mb"] / SPEED_UNIT,
        law.rate(state, speed, P, ops=ca) / law.state_scale,
    )
    frozen = ca.vertcat(0, 0, law.rate(state, 0, P, ops=ca) / law.state_scale)
    ode = ca.vertcat(T * (m * moving + (1 - m) * frozen), 0, 0, P["duration"] * (1 - m), 0, 0)
    vs = P["v_stick"] / SPEED_UNIT
    zero = ca.vertcat(
        # stop: reversal, or (armed) below the stick threshold; 1 once frozen
        m * (s * eta - a * vs) + (1 - m),
        # arming: becomes negative once faster than the threshold
        m * (1 - a) * (vs - s * eta) + (1 - m * (1 - a)),
        # speed maximum: the acceleration along s turns negative (scaled to ~1)
        m * s * force / (N + 1e-30) + (1 - m),
    )
    return dict(x=X, u=u, p=p, ode=ode, zero=zero, names=names)


@functools.cache
def arc_dae(model: Model) -> dict:
    """The slip DAE for identification arcs: the puller keeps stepping inside the arc.

    Same equations as :func:`slip_dae`, with xp(t) = u + Δxp·floor(fp·t) (u the puller
    position at the trigger, in µm) instead of a control per output, so one integrator
    serves arcs of any number of step intervals. Parameters: those of :func:`slip_dae`
    followed by fp (Hz).
    """
    d = slip_dae(model)
    names, p, P, X, u = _symbols(model)
    fp = ca.SX.sym("fp")
    t = ca.SX.sym("t")  # normalised time of the integrator, in [0, 1]
    t_phys = t * P["duration"] * TIME_UNIT
    xp = u + model.step(P) / LENGTH_UNIT * ca.floor(fp * t_phys + 1e-9)
    ode = ca.substitute(d["ode"], u, xp)
    zero = ca.substitute(d["zero"], u, xp)
    return dict(x=X, u=u, t=t, p=ca.vertcat(p, fp), ode=ode, zero=zero, names=names + ("fp",))


@functools.cache
def _transition(model: Model, extra_p: int = 0) -> ca.Function:
    """Freeze (stop), arm (stick threshold) or record the peak speed at an event."""
    names, p, P, X, u = _symbols(model)
    if extra_p:
        p = ca.vertcat(p, ca.SX.sym("extra", extra_p))
    idx = ca.SX.sym("index")
    t = ca.SX.sym("t")
    frozen = ca.vertcat(X[0], 0, X[2], 0, X[4], X[5], X[2], ca.fmax(X[7], ca.fabs(X[1])))
    armed = ca.vertcat(X[0], X[1], X[2], X[3], 1, X[5], X[6], X[7])
    peak = ca.vertcat(X[0], X[1], X[2], X[3], X[4], X[5], X[6], ca.fmax(X[7], ca.fabs(X[1])))
    post = ca.if_else(idx == 0, frozen, ca.if_else(idx == 1, armed, peak))
    return ca.Function(
        "freeze", [idx, t, X, ca.SX(0, 1), p, u], [post, ca.SX(0, 1)],
        ca.event_in(), ca.event_out(),
    )


@functools.cache
def slip_rhs(model: Model) -> ca.Function:
    """(X, xp_um, p) -> dX/d(normalised time), for Hermite event location."""
    d = slip_dae(model)
    return ca.Function("slip_rhs", [d["x"], d["u"], d["p"]], [d["ode"]], ["X", "xp_um", "p"], ["dX"])


@functools.cache
def slip_integrator(
    model: Model,
    plugin: str = "idas",
    grid: Sequence[float] = (1.0,),
    control_groups: None = None,
    reltol: float = 1e-7,
    abstol: float = 1e-9,
    events: bool | None = None,
    calc_ic: bool = True,
) -> ca.Function:
    """A cached integrator of the slip DAE over the normalised ``grid`` (in (0, 1]).

    ``plugin`` is ``idas`` (no events: the caller locates them) or ``rosenbrock``
    (zero-crossing events with the freezing transition, sensitivities include event
    times). The control xp takes one column per output time (the value on the interval
    ending there) or one column for the whole call. ``control_groups`` is not used:
    CasADi 3.8's rosenbrock control groups failed on creep tails.
    """
    d = slip_dae(model)
    dae = {k: d[k] for k in ("x", "u", "p", "ode")}
    opts: dict = dict(reltol=reltol, abstol=abstol)
    use_events = (plugin == "rosenbrock") if events is None else events
    if use_events:
        dae["zero"] = d["zero"]
        # the event work vector is sized by max_events: a huge bound costs ~1 s per call
        opts.update(transition=_transition(model), max_events=20_000, event_tol=1e-12)
    if plugin == "idas":
        opts.update(calc_ic=calc_ic, max_num_steps=200_000, disable_internal_warnings=True)
    elif plugin == "rosenbrock":
        opts.update(max_num_steps=200_000)
    grid = [float(g) for g in grid]
    return compiled(lambda extra: ca.integrator(f"slip_{plugin}", plugin, dae, 0.0, grid, {**opts, **extra}),
                    tag=f"slip_{plugin}_{len(grid)}")


def transition(model: Model, extra_p: int = 0) -> ca.Function:
    """The event transition Function (freeze / arm / peak) for a DAE with ``extra_p``
    parameters after the slip DAE's."""
    return _transition(model, extra_p)
