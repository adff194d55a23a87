"""Candidate effects for the sim-to-real diagnosis (DESIGN.md §4).

Each candidate is a model extension with its own parameter(s) whose null value gives
back the baseline. The simulator and the identification NLP carry every extension
(:mod:`identify.model.params`, kinds ``effect`` and ``measurement``), so a candidate is just a
choice of parameters to free, their null values, bounds, and the features of the data it
should touch. Adding an effect is one small subclass of :class:`Effect`; it registers
itself under its ``id``.

Two candidates are not nested in the baseline: the alternative aging laws
(``aging_logarithmic``, ``aging_logistic``) replace the exponential law. They are
compared by ΔAIC, not by a likelihood-ratio test.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from identify.model.params import TOPO_MODES, spec, topo_field_names, walk_names, walk_prior_sd

__all__ = ["Effect", "EFFECTS", "get_effect", "effect_ids"]

EFFECTS: dict[str, Effect] = {}

ROUGHNESS_START = 0.02
"""The rough track's first prior scale ρ (:class:`TopographyField`): a friction coefficient
varying by a few hundredths along the track, as a sinusoidal ripple's realistic 0.03."""
ROUGHNESS_FLOOR = 1e-4
"""Below this prior scale the field is flat for any data (μ to 1e-4: a few nm of slip)."""
TRACK_LENGTH_FACTOR = 1.25
MIN_TRACK_LENGTH = 5e-6
WALK_START = 1e-8
"""The camera's random walk's first intensity σ_w (m/√s; :class:`DriftWalk`): half the
withheld sets' 20 nm/√s, a wander of tens of nm over a run of seconds."""
WALK_FLOOR = 1e-11
"""Below this intensity the walk is nothing any run can show (0.1 nm over 100 s)."""


class Effect:
    """A candidate model extension.

    Class attributes
    ----------------
    id : str
        The name used by the CLI (``--effects``) and in results.
    parameters : tuple of str
        Model parameters freed when the candidate is tried.
    null : dict
        Values that give back the baseline. ``None``: the baseline's own (fixed) value.
    bounds : dict
        name -> (lower, upper) for the candidate fit (default: the parameter table's).
    law : str or None
        An alternative aging law that replaces the baseline's (non-nested candidate).
    touches : tuple of str
        Features of the data the effect should move (the ``where`` names).
    magnitude : (parameter, realistic value, unit shown)
        The parameter and value used to simulate a data set with the effect on (tests,
        benchmark), and its display unit.
    scope : "run", "device" or None
        One value of each parameter per run or per device (:mod:`identify.model.scopes`)
        instead of one for all. Such a candidate is bound to the data's runs
        (:meth:`bind`) before it is used: its parameters are then the scoped names.
    reference : bool
        For a per-device candidate: one device (the one with the most runs) keeps the
        null, the others are free: where only ratios between devices are determined (a
        spring constant, whose common factor μ·N/k absorbs).
    """

    id: ClassVar[str] = ""
    parameters: ClassVar[tuple] = ()
    null: ClassVar[Mapping[str, float | None]] = {}
    bounds: ClassVar[Mapping[str, tuple]] = {}
    law: ClassVar[str | None] = None
    touches: ClassVar[tuple] = ()
    magnitude: ClassVar[tuple] = ()
    scope: ClassVar[str | None] = None
    reference: ClassVar[bool] = False
    sets: ClassVar[tuple] = ()  # parameters it sets from the runs without fitting them (fixed_values)
    nuisance: ClassVar[tuple] = ()  # bases of parameters freed beside it that do not define it
    labels: tuple = ()  # bound: the runs or devices with a parameter of their own
    reference_label: str | None = None  # bound: the device kept at the null
    n_labels: int | None = None  # bound: how many runs or devices the data have in this scope

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.id:
            EFFECTS[cls.id] = cls()

    # ------------------------------------------------------------------ use
    @property
    def nested(self) -> bool:
        return self.law is None

    @property
    def global_twin(self) -> str | None:
        """The global candidate this per-run or per-device one nests (all its values equal
        give the global one back), or None. A per-device candidate with a reference does
        not nest its global one: the reference stays at the null where the global value
        moves every device."""
        if self.scope is None or self.reference:
            return None
        return type(self).__mro__[1].id or None

    @property
    def defining(self) -> tuple:
        """The parameters whose null defines the baseline (for topography its amplitude:
        wavelength and phase mean nothing at zero amplitude; never a nuisance, as motion
        blur's clock shifts, which mean nothing without a blur)."""
        if self.id == "topography":
            return self.parameters[:1]
        from identify.model.scopes import parse

        return tuple(n for n in self.parameters if parse(n)[0] not in self.nuisance)

    @property
    def description(self) -> str:
        doc = (type(self).__doc__ or "").strip().splitlines()
        return doc[0] if doc else self.id

    def null_values(self, baseline: Mapping[str, float]) -> dict:
        """The values of this candidate's parameters that give back ``baseline``."""
        return {n: (baseline[n] if self.null.get(n) is None else float(self.null[n])) for n in self.parameters}

    def bind(self, runs) -> Effect:
        """This candidate for ``runs`` (objects with ``name``, ``kind``, ``k`` and
        ``device``, as :class:`identify.fitting.rundata.RunData`): a per-run or per-device
        candidate gets one parameter per run (runs fitted by their frames: a creeping
        run's drift leaves no trace in its steady level) or per device, the others are
        returned as they are."""
        if self.scope is None or runs is None:
            return self
        from identify.model.scopes import device_of, label, scoped

        if self.scope == "run":
            order = [label(r.name) for r in runs if getattr(r, "kind", "events") == "events"]
        else:
            order = [device_of(r) for r in runs]
        counts = {lab: order.count(lab) for lab in dict.fromkeys(order)}
        labels = list(counts)
        ref = None
        if self.reference and labels:
            ref = max(sorted(labels), key=lambda lab: counts[lab])  # most runs; ties: first by name
            labels.remove(ref)
        bound = copy.copy(self)
        base = self.parameters
        bound.parameters = tuple(scoped(b, self.scope, lab) for b in base for lab in labels)
        bound.null = {scoped(b, self.scope, lab): self.null.get(b) for b in base for lab in labels}
        bound.bounds = {scoped(b, self.scope, lab): self.bounds[b] for b in base if b in self.bounds for lab in labels}
        bound.labels, bound.reference_label, bound.n_labels = tuple(labels), ref, len(counts)
        return bound

    def named(self, parameters) -> Effect:
        """This per-run or per-device candidate with the scoped ``parameters`` a refit freed
        (a record's own: its nulls' names), for reading the record without its runs."""
        if self.scope is None:
            return self
        bound = copy.copy(self)
        bound.parameters = tuple(parameters)
        return bound

    def applicable(self, free: tuple, law: str) -> str | None:
        """Why this candidate cannot extend a baseline with these free parameters and law
        (``None``: it can)."""
        if self.scope is not None and not self.labels and self.confounded_reason():
            return self.confounded_reason()
        if self.scope is not None and len(self.labels) <= 1 and self.n_labels is not None:
            # one value for the only run or device there is: the global candidate again
            what = "run fitted by its frames" if self.scope == "run" else "device"
            if not self.labels:
                return f"no {what} to give a value of its own"
            if not self.reference:
                return f"one {what} only: the same as the global candidate {type(self).__mro__[1].id}"
        if self.law is not None and self.law == law:
            return f"the baseline already uses the {law} law"
        taken = [n for n in self.parameters if n in free]
        if taken and self.law is None:
            return f"{', '.join(taken)} already free in the baseline"
        # a parameter free in another scope (global beside per-run, or per-device
        # beside global): the two would share the same residuals
        from identify.model.scopes import parse

        base = {parse(n)[0] for n in self.parameters}
        other = [n for n in free if parse(n)[0] in base]
        if other and self.law is None:
            return f"{scope_summary(other)} already free in the baseline, in another scope"
        return None

    def run_values(self, runs, magnitude: float | None = None, seed: int = 0) -> list:
        """Per run of ``runs`` (sequence of (name, device)), the values that switch a per-run
        or per-device effect on (withheld-effect data sets); [] for a global effect."""
        return []

    def fixed_values(self) -> dict:
        """Values of parameters the candidate sets but does not fit (the rough track's
        period), added to the current model's when it is tried."""
        return {}

    def priors(self, roughness: float | None = None) -> dict:
        """Standard deviations of zero-mean Gaussian priors on the candidate's parameters
        (:attr:`identify.fitting.options.FitOptions.priors`) at the prior scale
        ``roughness`` (default the candidate's first); {}: none."""
        return {}

    def prior_scale_text(self, scale: float) -> str:
        """The prior scale ``scale`` in words, with its unit."""
        return f"prior scale {scale:.3g}"

    def prior_scale_update(self, values: Mapping[str, float], edf: float) -> float:
        """The prior scale the evidence gives for these values of the candidate's penalised
        parameters and their effective degrees of freedom ``edf`` (MacKay's update); only
        for a candidate with :meth:`priors`."""
        raise NotImplementedError(f"{self.id} has no prior to update")

    def confounded_reason(self) -> str | None:
        """Why a bound per-device candidate has nothing to free (one device only), or None."""
        if self.scope == "device" and self.reference and self.n_labels == 1:
            return (f"one device only ({self.reference_label}): a factor for it is the global one, which the "
                    "friction coefficients absorb (μ·N/k sets every elongation); runs of a second device "
                    "would tell them apart")
        return None

    def nudges(self) -> list:
        """Starts off the null for parameters whose null sits on a bound (where the
        refit could not leave it by the local slope alone): the parameter table's typical
        scale, inside the bounds, with the other parameters from a fresh staged start (the
        baseline's have compensated for the missing effect: the paper's A = 0 fit raises
        μmin to shorten its slips, and from there A can only grow by moving μmin back)."""
        out = []
        for n in self.parameters:
            lo, hi = self.bounds.get(n, (spec(n).lower, spec(n).upper))
            null = self.null.get(n)
            if null is not None and null in (lo, hi):
                step = spec(n).scale if null == lo else -spec(n).scale
                out.append({n: float(min(max(null + step, lo), hi)), "_staged": True})
        return out

    def scaled_magnitude(self, scale: float) -> float:
        """The effect's parameter at ``scale`` times its realistic departure from the null
        (a detection-limit sweep): a factor whose null is 1 (``step_scale`` 1.05) scales
        its excess, 1.05 -> 1.015 at 0.3, not to 0.315; a null taken from the baseline
        (None) counts as 0."""
        name, value, _ = self.magnitude
        null = self.null.get(name)
        null = 0.0 if null is None else float(null)
        return null + scale * (float(value) - null)

    def simulation_values(self, magnitude: float | None = None, values: Mapping[str, float] | None = None) -> dict:
        """Parameter values that switch the effect on (withheld-effect data sets, the
        regime screen); ``values``: the model's others (an aging law's own parameters are
        set from them)."""
        name, value, _ = self.magnitude
        return {name: float(value if magnitude is None else magnitude)}

    def to_json(self) -> dict:
        return dict(id=self.id, parameters=list(self.parameters), law=self.law, touches=list(self.touches),
                    description=self.description)

    def __repr__(self) -> str:
        return f"<Effect {self.id}: {', '.join(self.parameters) or self.law}>"


def effect_ids() -> tuple:
    return tuple(EFFECTS)


def get_effect(name: str, runs=None) -> Effect:
    """The candidate ``name``; bound to ``runs`` where it has one parameter per run or
    device (:meth:`Effect.bind`)."""
    try:
        eff = EFFECTS[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; choose from {', '.join(EFFECTS)}") from None
    return eff.bind(runs)


# ----------------------------------------------------------------------------- library
class VelocityStrengthening(Effect):
    """Velocity strengthening: μ = ψ + A·ln(1 + |ẋ|/vc) (Eq. 18); null A = 0.

    Only a candidate when the baseline fixes A (the paper's own story: without it the
    simulated slips were too long)."""

    id = "velocity_strengthening"
    parameters = ("A",)
    null = {"A": 0.0}
    bounds = {"A": (0.0, 0.2)}
    touches = ("slip_length", "post_slip_level", "creep_level")
    magnitude = ("A", 0.015, "-")

    def applicable(self, free, law):
        if "A" in free:
            return "A already free in the baseline"
        return None


class AgingLogarithmic(Effect):
    """Logarithmic (Dieterich–Ruina) aging: ψ = μ0 + B·ln(1 + vc·φ/dc), dφ/dt = 1 − |ẋ|φ/dc.

    Replaces the exponential law (μmax, μmin, τ become μ0, B): non-nested, scored by ΔAIC."""

    id = "aging_logarithmic"
    law = "logarithmic"
    parameters = ("mu_0", "B")
    touches = ("static_friction", "static_friction_vs_rest")
    magnitude = ("law", "logarithmic", "")

    def simulation_values(self, magnitude=None, values=None):
        """μ0 and B with the exponential law's static friction at similar rests:
        μs(t) = μ0 + B·ln(1 + vc·t/dc) through μmin at 0 and μmax at 1 s of rest."""
        if values is None:
            return {}
        vc, dc = values["vc"], values["dc"]
        B = (values["mu_max"] - values["mu_min"]) / math.log(1 + vc * 1.0 / dc)
        return dict(mu_0=float(values["mu_min"]), B=float(B))


class AgingLogistic(Effect):
    """Logistic (Carlson–Batista) aging: dψ/dt = (ψ − μmin)(μmax − ψ)/(τΔ) − (ψ − μmin)|ẋ|/dc.

    Replaces the exponential law with the same parameters: non-nested, scored by ΔAIC."""

    id = "aging_logistic"
    law = "logistic"
    parameters = ("mu_max", "mu_min", "tau")
    touches = ("static_friction", "static_friction_vs_rest")
    magnitude = ("law", "logistic", "")

    def simulation_values(self, magnitude=None, values=None):
        return {}  # the same parameters, another curve shape


class Rejuvenation(Effect):
    """Finite memory length: dψ/dt ∋ −(ψ − μmin)·|ẋ|/dc (Eq. 15); null dc = the baseline's.

    A longer dc keeps part of the aged contact through a slip: higher, longer slips."""

    id = "rejuvenation"
    parameters = ("dc",)
    null = {"dc": None}
    bounds = {"dc": (1e-10, 1e-5)}
    touches = ("slip_length", "static_friction")
    magnitude = ("dc", 1e-6, "m")


class Damping(Effect):
    """Extra viscous damping: m·ẍ = F_s − μN − (c + c_extra)·ẋ; null c_extra = 0."""

    id = "damping"
    parameters = ("c_extra",)
    null = {"c_extra": 0.0}
    bounds = {"c_extra": (-3e-7, 1e-3)}
    touches = ("slip_length",)
    magnitude = ("c_extra", 2e-5, "N s/m")


class SpringNonlinearity(Effect):
    """Nonlinear spring: F_s = k·e·(1 + β·e²); null β = 0."""

    id = "spring_nonlinearity"
    parameters = ("beta",)
    null = {"beta": 0.0}
    bounds = {"beta": (-1e10, 1e10)}
    touches = ("static_friction", "slip_length", "post_slip_level")
    magnitude = ("beta", 1e9, "1/m^2")


class SpringConstant(Effect):
    """Spring-constant error: true k = s_k·k_nominal; null s_k = 1.

    Nearly absorbed by the friction coefficients (μ·Nb/k sets every elongation)."""

    id = "spring_constant"
    parameters = ("k_scale",)
    null = {"k_scale": 1.0}
    bounds = {"k_scale": (0.5, 2.0)}
    touches = ("static_friction", "slip_length")
    magnitude = ("k_scale", 1.15, "-")


class LoadOffset(Effect):
    """Adhesion-like extra normal force: N = Nb + F_a (Eq. 6); null F_a = 0."""

    id = "load_offset"
    parameters = ("load_offset",)
    null = {"load_offset": 0.0}
    bounds = {"load_offset": (-5e-6, 5e-5)}
    touches = ("static_friction", "slip_length", "conditions")
    magnitude = ("load_offset", 2e-6, "N")


class LoadScale(Effect):
    """Normal-load calibration error: true Nb = s_N·Nb_nominal; null s_N = 1.

    Exactly absorbed by the friction coefficients when μmax, μmin and A are free."""

    id = "load_scale"
    parameters = ("load_scale",)
    null = {"load_scale": 1.0}
    bounds = {"load_scale": (0.5, 2.0)}
    touches = ("static_friction", "slip_length")
    magnitude = ("load_scale", 1.15, "-")


class StepSize(Effect):
    """Puller step differs from the metadata: Δx_true = s_x·Δx_nominal; null s_x = 1."""

    id = "step_size"
    parameters = ("step_scale",)
    null = {"step_scale": 1.0}
    bounds = {"step_scale": (0.5, 2.0)}
    touches = ("stick_slope", "post_slip_level")
    magnitude = ("step_scale", 1.05, "-")


class Topography(Effect):
    """Friction varying along the track, the same for every run of a device:
    μ_topo(x) = a·sin(2πx/λ + φ); null a = 0.

    Its wavelength and phase are not defined at a = 0: the candidate starts from the
    ripple that the ``position`` feature of the diagnosis finds in the residuals."""

    id = "topography"
    parameters = ("topo_amp", "topo_phase", "topo_wavelength")
    null = {"topo_amp": 0.0, "topo_phase": 0.0, "topo_wavelength": None}
    # wavelengths below ~1 µm (twenty steps) would let the ripple give every slip its own
    # capacity: with slip positions known to tens of nm it then fits noise, not a track
    bounds = {"topo_amp": (-0.3, 0.3), "topo_wavelength": (1e-6, 1e-4), "topo_phase": (-20.0, 20.0)}
    touches = ("position", "static_friction", "slip_length")
    magnitude = ("topo_amp", 0.03, "-")
    sets = ("topo_length",)

    def simulation_values(self, magnitude=None, values=None):
        return {"topo_amp": float(0.03 if magnitude is None else magnitude), "topo_wavelength": 4e-6,
                "topo_phase": 0.7}


class TopographyField(Effect):
    """A rough track: friction varying along it as a smooth random field shared by every
    run, μ_topo(x) = Σⱼ cⱼ·cos(2πjx/L) + sⱼ·sin(2πjx/L); null every coefficient 0.

    The roughness is the data's to choose. The coefficients carry a Gaussian prior
    cⱼ, sⱼ ~ N(0, (ρ/j)²) (a field of finite slope variance: mode j's share falls as 1/j),
    and ρ is set by the evidence (MacKay's update ρ² = Σⱼ j²·(cⱼ² + sⱼ²)/γ, γ the
    effective degrees of freedom the prior leaves; :func:`roughness_update`). The
    likelihood-ratio test and the information criteria count γ, not the
    2·:data:`identify.model.params.TOPO_MODES` coefficients. L is 1.25 times the longest
    travel of the runs (the series need not repeat on the track); its magnitude, for a
    withheld data set, is the track's rms friction variation."""

    id = "topography_field"
    parameters = topo_field_names()
    null = {n: 0.0 for n in topo_field_names()}
    bounds = {n: (-0.3, 0.3) for n in topo_field_names()}
    touches = ("position", "static_friction", "slip_length")
    magnitude = ("topo_amp", 0.03, "-")
    sets = ("topo_length",)
    length: float | None = None  # bound: L, m
    roughness: float = ROUGHNESS_START

    def bind(self, runs) -> Effect:
        """This candidate with L set from the runs' travel (their block positions)."""
        travel = [float(np.nanmax(r.plateau_level0)) for r in (runs or ())
                  if getattr(r, "plateau_level0", None) is not None and len(r.plateau_level0)]
        if not travel:
            return self
        bound = copy.copy(self)
        bound.length = max(TRACK_LENGTH_FACTOR * max(travel), MIN_TRACK_LENGTH)
        return bound

    def fixed_values(self) -> dict:
        return {} if self.length is None else {"topo_length": float(self.length)}

    def prior_scale_text(self, scale: float) -> str:
        return f"roughness ρ = {scale:.3g} (friction; mode j's coefficients have sd ρ/j)"

    def priors(self, roughness: float | None = None) -> dict:
        rho = float(self.roughness if roughness is None else roughness)
        return {n: rho / int(n[6:]) for n in self.parameters}

    def prior_scale_update(self, values, edf):
        return roughness_update(values, edf)

    def simulation_values(self, magnitude=None, values=None):
        """A rough track of rms ``magnitude`` (over its period) on a period of 50 µm: one
        fixed draw of the prior's 1/j spectrum, on a period the fit's own L (set by the
        travel) does not share, so that its series has to approximate the track, not
        copy it."""
        rms = float(self.magnitude[1] if magnitude is None else magnitude)
        rng = _rng(0, 3)
        j = np.repeat(np.arange(1, TOPO_MODES + 1), 2)
        coef = rng.standard_normal(j.size) / j
        coef *= rms / math.sqrt(0.5 * float(coef @ coef))
        return {"topo_length": 5e-5, **dict(zip(topo_field_names(), (float(c) for c in coef)))}


def roughness_update(values: Mapping[str, float], edf: float, floor: float = ROUGHNESS_FLOOR) -> float:
    """MacKay's evidence update of the rough track's prior scale ρ: Σⱼ j²·(cⱼ² + sⱼ²)/γ,
    γ the effective degrees of freedom of the coefficients (at least ``floor``)."""
    ss = sum(int(n[6:]) ** 2 * float(values.get(n, 0.0)) ** 2 for n in topo_field_names())
    return max(math.sqrt(ss / max(edf, 0.5)), floor)


class Drift(Effect):
    """Slow drift of the measured elongation: e_meas = e + r_d·t; null r_d = 0."""

    id = "drift"
    parameters = ("drift_rate",)
    null = {"drift_rate": 0.0}
    bounds = {"drift_rate": (-1e-5, 1e-5)}
    touches = ("time", "stick_slope", "post_slip_level")
    magnitude = ("drift_rate", 5e-8, "m/s")


class DriftPerRun(Drift):
    """Drift at each run's own rate: e_meas = e + r_i·t in run i; null r_i = 0 for every run.

    A camera or a chip creeping thermally, at a rate and sign of its own in each run."""

    id = "drift_per_run"
    scope = "run"
    touches = ("time_by_run", "stick_slope", "post_slip_level")

    def run_values(self, runs, magnitude=None, seed=0):
        """Rates of the magnitude's size, 0.5-1.5× it, signs alternating from run to run."""
        m = float(self.magnitude[1] if magnitude is None else magnitude)
        rng = _rng(seed, 1)
        return [{"drift_rate": m * (-1) ** i * rng.uniform(0.5, 1.5)} for i in range(len(runs))]


class DriftWalk(DriftPerRun):
    """Drift at each run's own rate with a random walk of the camera's zero besides:
    e_meas = e + r_i·t + W_i(t) in run i; null r_i = 0 and W_i = 0.

    A camera's zero that wanders as well as creeps. W_i is a Wiener process of intensity
    σ_w (m/√s), written as its Karhunen–Loève series over the run's span T_i,
    Σₘ c_im·√2·sin((m − ½)π·t/T_i) (:data:`identify.model.params.WALK_MODES` modes), whose
    coefficients are independent with standard deviation σ_w·√T_i/((m − ½)π): that is
    their prior, and σ_w is set by the evidence as a rough track's roughness is
    (:meth:`prior_scale_update`). The likelihood-ratio test and the information criteria
    count the effective degrees of freedom the prior leaves, and a rate's interval carries
    the trend the walk gives its run."""

    id = "drift_walk"
    parameters = ("drift_rate",) + walk_names()
    null = {n: 0.0 for n in ("drift_rate",) + walk_names()}
    bounds = {"drift_rate": (-1e-5, 1e-5), **{n: (-1e-5, 1e-5) for n in walk_names()}}
    roughness: float = WALK_START  # σ_w, m/√s
    spans: Mapping[str, float] | None = None  # bound: each run's span T_i, s

    def bind(self, runs) -> Effect:
        """One rate and one walk per run fitted by its frames, with the runs' spans."""
        bound = super().bind(runs)
        if bound is self:
            return self
        from identify.model.scopes import label

        bound.spans = {label(r.name): float(r.span_s) for r in runs
                       if label(r.name) in bound.labels and math.isfinite(getattr(r, "span_s", math.nan))}
        return bound

    def _modes(self):
        """(scoped name, m, T_i) of every walk coefficient of the bound runs."""
        from identify.model.scopes import scoped

        return [(scoped(n, "run", lab), m, T) for lab, T in (self.spans or {}).items()
                for m, n in enumerate(walk_names(), start=1)]

    def prior_scale_text(self, scale: float) -> str:
        return f"walk intensity σ_w = {scale * 1e9:.3g} nm/√s"

    def priors(self, roughness: float | None = None) -> dict:
        sw = float(self.roughness if roughness is None else roughness)
        return {n: walk_prior_sd(sw, m, T) for n, m, T in self._modes()}

    def prior_scale_update(self, values, edf):
        """σ_w² = Σ c_im²·((m − ½)π)²/T_i over the effective degrees of freedom."""
        ss = sum(float(values.get(n, 0.0)) ** 2 * ((m - 0.5) * math.pi) ** 2 / T for n, m, T in self._modes())
        return max(math.sqrt(ss / max(edf, 0.5)), WALK_FLOOR)


class SpringConstantPerDevice(SpringConstant):
    """Spring constants off per device: true k = s_d·k_nominal on device d; null s_d = 1.

    One device, the one with the most runs, is the reference kept at 1. Only ratios
    between devices are determined (a common factor is absorbed by the friction
    coefficients): with a single device there is nothing to free."""

    id = "spring_constant_per_device"
    scope = "device"
    reference = True

    def run_values(self, runs, magnitude=None, seed=0):
        return _on_one_device(self, runs, magnitude)


class LoadOffsetPerDevice(LoadOffset):
    """Load offset per device: N = Nb + F_a,d on device d; null F_a,d = 0 for every device.

    An adhesion-like extra normal force of each device's own."""

    id = "load_offset_per_device"
    scope = "device"

    def run_values(self, runs, magnitude=None, seed=0):
        return _on_one_device(self, runs, magnitude)


def _on_one_device(eff: Effect, runs, magnitude) -> list:
    """A per-device effect's withheld values: its magnitude on every run of one device
    (the first of those with the fewest runs: never the reference a per-device candidate
    keeps at its null, the one with the most), the null on the others."""
    name, value, _ = eff.magnitude
    m = float(value if magnitude is None else magnitude)
    devs = [dev for _, dev in runs]
    counts = {d: devs.count(d) for d in dict.fromkeys(devs)}
    ref = max(sorted(counts), key=lambda d: counts[d])  # as Effect.bind chooses it
    off = min((d for d in counts if d != ref), key=lambda d: counts[d], default=ref)
    return [{name: m if dev == off else float(eff.null[name])} for dev in devs]


def scope_summary(names) -> str:
    """Parameter names grouped by base and scope, short: ``drift_rate (per run, 8 values)``."""
    from identify.model.scopes import parse

    groups: dict = {}
    for n in names:
        base, scope, _ = parse(n)
        groups.setdefault((base, scope), []).append(n)
    return ", ".join(base if scope is None else f"{base} (per {scope}, {len(v)} value{'s' * (len(v) > 1)})"
                     for (base, scope), v in groups.items())


def _rng(seed: int, stream: int):
    import numpy as np

    return np.random.default_rng([int(seed), 7_000 + stream])


class MotionBlur(Effect):
    """Motion blur: each frame averages e over an exposure T on its timestamp; null T = 0.

    A window straddling a slip reads a level between the plateaus: the frames around the
    slips are observed one by one (``FitOptions.drop_frames``, which the diagnosis turns on
    when this candidate is tried). Where the steps fall is estimated from the frames,
    and a blurred exposure moves that estimate: bound to runs with such frames, the
    candidate frees a clock shift per run besides T (``clock_shift@run:NAME``, within
    half a step period), so the window is taken as centred (``exposure_align``): a shift
    of the window on the timestamp is the same as a shift of the clock. With frames
    placed symmetrically in the step interval and windows shorter than their distance
    to the steps, the data cannot see the blur at all."""

    id = "motion_blur"
    parameters = ("exposure",)
    null = {"exposure": 0.0}
    bounds = {"exposure": (0.0, 1e-2)}
    touches = ("post_slip_level",)
    magnitude = ("exposure", 2e-3, "s")
    nuisance = ("clock_shift",)

    def bind(self, runs) -> Effect:
        """This candidate with a clock shift for each run whose frames around its slips
        are observed (:attr:`identify.fitting.rundata.RunData.drops`)."""
        from identify.model.scopes import label, scoped

        dropped = [r for r in (runs or ()) if getattr(r, "drops", False) and getattr(r, "kind", "") == "events"]
        if not dropped:
            return self
        bound = copy.copy(self)
        shifts = {scoped("clock_shift", "run", label(r.name)): 0.5 / r.fp for r in dropped}
        bound.parameters = ("exposure", *shifts)
        bound.null = {"exposure": 0.0, **{n: 0.0 for n in shifts}}
        bound.bounds = {"exposure": (0.0, 1e-2), **{n: (-h, h) for n, h in shifts.items()}}
        return bound

    def named(self, parameters) -> Effect:
        bound = copy.copy(self)
        bound.parameters = tuple(parameters) or self.parameters
        return bound


class StickThreshold(Effect):
    """Stick threshold: a block slower than v_stick is held while |F_s| ≤ (ψ + A·ln(1 +
    v_stick/vc))·N (the simulator's stick option, a Karnopp band); null = the baseline's."""

    id = "stick_threshold"
    parameters = ("v_stick",)
    null = {"v_stick": None}
    bounds = {"v_stick": (0.0, 1e-2)}
    touches = ("slip_length", "creep_level")
    magnitude = ("v_stick", 1e-4, "m/s")


def display(name: str, value: float) -> str:
    """A parameter value in its display unit."""
    s = spec(name)
    v = s.to_display(value)
    unit = "" if s.shown_unit == "-" else s.shown_unit
    return f"{v:.4g} {unit}".strip() if math.isfinite(v) else "nan"
