"""The fit's options and its error: what to fit, how, and what a fit that cannot be done raises."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace

from identify.fitting.arcs import ARC_ABSTOL, ARC_RELTOL
from identify.fitting.solver_options import SOLVER_FIELDS, GaussNewtonOptions, IpoptOptions, StopOptions
from identify.model.laws import get_law
from identify.model.params import spec, walk_names
from identify.model.plausible import check_parameters
from identify.model.scopes import is_scoped, parse
from identify.model.symbolic import Model

DEFAULT_FREE = ("mu_max", "mu_min", "tau", "A")
SEQUENCE_PASSES = ("triggers", "missed", "batch", "ambiguous", "misfit")


def _is_free(name: str, free: tuple) -> bool:
    """Whether ``name`` is free: named in ``free``, or one run's or device's value of a
    ``base@run`` or ``base@device`` there (written out for every run once the runs are known)."""
    if name in free:
        return True
    if not is_scoped(name):
        return False
    base, scope, _ = parse(name)
    return f"{base}@{scope}" in free


class FitError(ValueError):
    """Nothing could be fitted (every run was left out, or the solver failed).

    ``excluded`` lists (run name, why) for runs that were left out; ``regime_runs`` those
    of them left out for their regime (:class:`identify.fitting.regime_check.RegimeRun`), and
    ``values`` the parameter values their regime was judged at (the diagnosis screens
    its candidates on them, :mod:`identify.diagnosis.regime_screen`); ``used`` the runs that could
    be used, when they were too few to fix the free parameters, and ``counts`` then their
    (observations, free dimensions)."""

    def __init__(self, message: str, excluded=(), regime_runs=(), values=None, used=(), counts=None):
        super().__init__(message)
        self.excluded = list(excluded)
        self.regime_runs = list(regime_runs)
        self.values = dict(values or {})
        self.used = list(used)
        self.counts = counts


@dataclass(frozen=True)
class FitOptions:
    """How to fit.

    Parameters
    ----------
    law : str
        Aging law (``exponential``, ``logarithmic``, ``logistic``).
    free : tuple of str
        Parameters estimated (any model parameter: friction, platform or effect).
    fixed : dict
        Values for parameters that are not free (default: the coating's preset).
    bounds : dict
        name -> (lower, upper) for free parameters (default: the parameter table's).
    start : dict
        Start values for free parameters (default: the reduced analysis, else the preset).
    priors : dict
        name -> standard deviation (SI) of a Gaussian prior centred on 0, for free
        parameters whose size the data should have to argue for (the rough track's
        coefficients, :class:`identify.model.effects.TopographyField`). Each adds a residual
        θ/σ; the χ² the fit reports includes them, and
        :meth:`identify.fitting.problem.Problem.penalised_counts` separates them and
        counts the free dimensions as the penalty implies.
    drop_frames : bool
        Observe the frames around each slip one by one instead of leaving them out of
        the plateaus (:func:`identify.fitting.rundata.drop_frames`): a frame whose
        exposure straddles a slip reads a level between the plateaus, which only a
        blurred exposure (``exposure``, placed by ``exposure_align``) explains. The
        motion-blur candidate of the diagnosis fits this way, against its null refitted
        on the same frames.
    walk_intensity : float or None
        σ_w (m/√s) of a random walk of the camera's zero: each free walk coefficient of a
        run (``walk_m@run:NAME``, or ``walk_m@run`` for every run; the series of
        :class:`identify.model.effects.DriftWalk`) without a prior of its own in
        ``priors`` gets the Wiener process's, sd σ_w·√T/((m − ½)π) with T the run's
        span (:func:`identify.model.params.walk_prior_sd`). Without it free walk
        coefficients are fitted unpenalised: six free shapes per run, which absorb what
        they can of any misfit. ``identify fit --walk-nm-per-sqrt-s`` sets it and frees
        the six modes of every run.
    free_offset : bool
        Estimate a per-run elongation zero offset.
    use_creep_runs : bool
        Use runs without resolvable slips as steady-sliding observations when the model
        at the start parameters creeps there.
    max_arc_steps : int
        Largest number of puller steps one slip arc may span.
    arc_reltol, arc_abstol : float
        Tolerances of the arcs (scaled states); why the defaults: ``identify.fitting.arcs.ARC_RELTOL``.
    arc_jacobian : {"forward", "central", "exact"}
        The arcs' derivatives while the solver iterates: finite differences (``forward``,
        default: one integration per input instead of two; ``central``), or ``exact``:
        IDAS sensitivities through the stop time (:mod:`identify.fitting.exact_arcs`), 30-40×
        the cost per arc and not shared among arcs. The covariance always uses central
        differences.
    share_arc_jacobian : bool
        Let slips whose inputs nearly agree share one slip's forward differences
        (``identify.fitting.arcs.SHARE_TOL``; default True): a run's slips repeat nearly one
        cycle, and most of an iteration's integrations went to derivatives known already.
    solver : {"ipopt", "gauss-newton"}
        ``ipopt`` (default): Ipopt (interior point, filter line search) with the
        Gauss–Newton Hessian and exact constraint Jacobians, stopped by the statistical
        test of :mod:`identify.fitting.convergence`. ``gauss-newton``: the toolkit's own
        constrained Gauss–Newton SQP with an ℓ1-merit line search (Bock's method for
        multiple shooting); it ends where Ipopt ends on the benchmark sets, 3-4×
        slower, but on some hard data sets in a better basin (README, Known limits).
    staged_start : bool
        Start from the trigger and slip-length stages of :mod:`identify.fitting.start`.
    max_iter, tol : iteration limit; tolerance on the relative step and feasibility.
    stop : StopOptions
        When a solve has converged (both solvers): the statistical test's tolerances.
    gauss_newton : GaussNewtonOptions
        The Gauss–Newton SQP's own search and stopping rules.
    ipopt : IpoptOptions
        What Ipopt is told besides ``max_iter`` and ``tol``.
    threads : int
        Threads for the arc evaluations.
    multistart : int
        Extra starts drawn around the first (log-normal, 30 %) with ``seed``.
    auto_starts : int
        When the solution still looks wrong after the start before or after staging was
        tried (not converged, reduced χ² above 2, a parameter at a bound), this many more
        starts spread over each parameter's plausible range (a decade either side of the
        suspect solution and of the coating's preset for log-scaled parameters, ±40 % for
        the others; τ also over the data's rest times), a Latin hypercube seeded by
        ``seed``; the best solution is kept and the report's start line says so. 0 turns
        it off.
    check_platform : bool
        Refuse fixed and start values outside what a contact on the platform can
        plausibly have (:data:`identify.model.plausible.PARAMETER_RANGES`: ``tau = 67.4``
        is milliseconds typed for seconds), naming the likely unit slip; False takes them.
    sequence_trials : int
        Trials of the last mode-sequence pass (:func:`identify.fitting.mode_sequence.passes.misfit_triggers`:
        local changes where the model's triggers misfit, each a short re-solve of the
        changed run alone with the parameters held; a kept change is solved jointly);
        0 turns it off. Data whose triggers fit pay none.
    sequence_passes : tuple of str
        The mode-sequence repairs the fit makes, of ``triggers`` (slip triggers moved
        where their residuals put them), ``missed`` (slips the detection missed
        inserted), ``batch`` (a run's many triggers a step off moved in one trial),
        ``ambiguous`` (the other step of triggers the frames leave ambiguous tried) and
        ``misfit`` (local changes where triggers still misfit, ``sequence_trials`` of
        them). Default all; ``()`` fits the sequence as detected.
    scale_covariance : bool
        Scale the model-based covariance by the reduced χ² (lmfit's default).
    free_phase : bool
        Estimate per run the phase of the step interval at which its slips recur,
        bounded to [0, 1] (the interval constraint for what the run's slips share, with a
        weak uniform prior), instead of taking the middle. A stick-slip cycle locks its
        triggers at one phase (measured 0.71 on a k = 20.3 N/m, 30 µN, 100 Hz run, the
        same from any start), which the middle pulls on: on three calibration repeats the
        bounded phases removed τ's bias (z −1.5…−2.1 → 0.2…0.4) but made its standard
        error 3–5× larger and the fit 5–10× slower, ending in a failed line search. Off
        by default.
    arc_start : {"aged", "mid"}
        The contact state a slip arc starts from. ``aged`` (default): the previous
        slip's end state aged over the rest, a shooting variable per slip (its position
        in the trigger interval) tied to it by a constraint, as in the simulator; a
        run's first slip from an estimated initial contact (uniform prior over its
        interval: the contact before the run is not observed).
        ``mid``: every arc starts from the state whose capacity sits in the middle of its
        trigger interval (a valid trigger for any parameters, the model off by up to
        half an interval of capacity, ~0.5 nm of slip length: invisible at 90 nm, but
        ~10 σ on noiseless traces).
    covariance : {"robust", "cluster", "model"}
        ``robust`` (default): the slips of a run share a phase error, as far as the
        spread of their trigger positions says (an exchangeable correlation per run, the
        expected meat of a sandwich); ``cluster``: cluster-robust by run from the
        realised residuals (few runs make it run small); ``model``: every residual
        independent.
    trigger : {"uniform", "interval"}
        How the data's trigger step enters. ``uniform`` (default): a residual
        √12·(s − φ) per slip, s the capacity's position in its step interval, φ the
        run's phase — a Gaussian stand-in (same mean and variance) for the flat
        likelihood of a position known only to lie in the interval; smooth, it guides
        the mode-sequence repairs and gives the triggers their share of the covariance.
        It pulls every s towards φ, which biases the estimates where the frames leave
        nothing to pull against: on noiseless data by ~2e-3 relative. ``interval``: the
        flat likelihood, 0 ≤ s ≤ 1 as bounds on the shooting variables and no trigger
        residual — consistent as the noise vanishes; for noiseless or nearly noiseless
        data. The fit is done with the uniform encoding (start, solves, mode sequence)
        and then solved once more from its solution with the interval; a re-solve that
        does not converge is not kept (the report's start line says so). Two caveats:
        the bounds are the plain interval [F_s(e − Δx), F_s(e)], without the aging
        during the last step that the uniform residual subtracts from its lower end
        (:meth:`identify.fitting.problem.Problem.position`), so starts a step early are admitted;
        and the covariance holds the frames' information only. On noisy data that is
        little: the triggers are where μmax and τ show, and bounds that are not active
        add nothing to a local covariance (measured on two 90 nm runs: the re-solve
        `Stalled`, standard errors of 1000 % and more). Needs ``arc_start="aged"``.
        Measured on two noiseless runs simulated at tolerance 1e-9, from 10 % off:
        uniform −2.3e-3 / −4.2e-4 / −3.8e-3 / +1.5e-3 (μmax, μmin, τ, A), interval within
        4e-5 of the truth (6e-5 from 5 % off).
    """

    law: str = "exponential"
    free: tuple = DEFAULT_FREE
    fixed: Mapping[str, float] = field(default_factory=dict)
    bounds: Mapping[str, tuple] = field(default_factory=dict)
    start: Mapping[str, float] = field(default_factory=dict)
    priors: Mapping[str, float] = field(default_factory=dict)
    walk_intensity: float | None = None
    drop_frames: bool = False
    free_offset: bool = False
    use_creep_runs: bool = True
    max_arc_steps: int = 64
    arc_reltol: float = ARC_RELTOL
    arc_abstol: float = ARC_ABSTOL
    arc_jacobian: str = "forward"
    share_arc_jacobian: bool = True
    solver: str = "ipopt"
    staged_start: bool = True
    max_iter: int = 100
    tol: float = 1e-8
    threads: int = 2
    multistart: int = 0
    sequence_trials: int = 64
    sequence_passes: tuple = SEQUENCE_PASSES
    seed: int | None = None
    scale_covariance: bool = True
    covariance: str = "robust"
    free_phase: bool = False
    arc_start: str = "aged"
    trigger: str = "uniform"
    stick_speed: str = "check"
    auto_starts: int = 4
    check_platform: bool = True
    stop: StopOptions = field(default_factory=StopOptions)
    gauss_newton: GaussNewtonOptions = field(default_factory=GaussNewtonOptions)
    ipopt: IpoptOptions = field(default_factory=IpoptOptions)

    def evolve(self, **changes) -> FitOptions:
        """A copy with ``changes``: the options' own fields, or a field of ``stop``,
        ``gauss_newton`` or ``ipopt`` by its name (``evolve(stall_tol=1.0, max_iter=20)``).

        Raises
        ------
        ValueError
            For a name that is no option's field (the message names it).
        """
        own = {f.name for f in fields(self)}
        nested = {"stop": {}, "gauss_newton": {}, "ipopt": {}}
        top = {}
        for name, value in changes.items():
            owner = [attr for attr, cls in _NESTED.items() if name in SOLVER_FIELDS[cls]]
            if name in own:
                top[name] = value
            elif owner:
                nested[owner[0]][name] = value
            else:
                raise ValueError(f"{name!r} is not a field of FitOptions, StopOptions, GaussNewtonOptions "
                                 "or IpoptOptions")
        for attr, sub in nested.items():
            if sub:
                top[attr] = replace(top.get(attr, getattr(self, attr)), **sub)
        if not self.free and "free" not in top:
            # a copy that holds every parameter (a mode-sequence trial's,
            # identify.fitting.mode_sequence.trials.held_options) stays one: replace()
            # would run the checks a fit's options must pass, and refuse it
            out = copy.copy(self)
            for name, value in top.items():
                object.__setattr__(out, name, value)
            return out
        return replace(self, **top)

    def __post_init__(self):
        get_law(self.law)
        free = tuple(self.free)
        object.__setattr__(self, "free", free)
        if not free:
            raise ValueError("free: at least one parameter must be free")
        from identify.fitting.problem import MEASUREMENT

        model = Model(get_law(self.law))
        allowed = set(model.parameter_names) | set(MEASUREMENT)
        for name in free:
            if is_scoped(name):
                try:
                    parse(name)
                except ValueError as err:
                    raise ValueError(f"free: {err}") from None
            if parse(name)[0] not in allowed:
                raise ValueError(
                    f"free: {name!r} is not a parameter of the {self.law} model; "
                    f"choose from {', '.join(model.parameter_names + MEASUREMENT)}"
                )
        if len(set(free)) != len(free):
            raise ValueError(f"free: {free} lists a parameter twice")
        for name, value in dict(self.fixed).items():
            spec(name).check(value, "fixed ")
            if name in free:
                raise ValueError(f"{name} is both free and fixed")
        for name, value in dict(self.start).items():
            spec(name).check(value, "start ")
        if self.check_platform:
            check_parameters(self.fixed, "fixed ")
            check_parameters(self.start, "start ")
        for name, (lo, hi) in dict(self.bounds).items():
            if not _is_free(name, free):
                raise ValueError(f"bounds: {name} is not free")
            if not lo < hi:
                raise ValueError(f"bounds: {name} needs lower < upper, got ({lo}, {hi})")
        for name, sd in dict(self.priors).items():
            if not _is_free(name, free):
                raise ValueError(f"priors: {name} is not free")
            if not (isinstance(sd, (int, float)) and math.isfinite(sd) and sd > 0):
                raise ValueError(f"priors: {name} needs a standard deviation > 0, got {sd!r}")
        if self.walk_intensity is not None:
            sw = self.walk_intensity
            if not (isinstance(sw, (int, float)) and math.isfinite(sw) and sw > 0):
                raise ValueError(f"walk_intensity = {sw!r}: must be a random walk's intensity > 0, in m/√s")
            if sw > 1e-4:  # (100 µm/√s: a camera's zero wandering by the whole travel in a second)
                raise ValueError(f"walk_intensity = {sw!r} m/√s: far beyond any camera's wander; it is in m/√s "
                                 f"(20 nm/√s is 2e-8), did you give it in nm/√s?")
            shared = [n for n in free if n in walk_names()]
            if shared:
                raise ValueError(f"walk_intensity: {shared[0]} is free as one walk shared by every run; a "
                                 f"camera's zero wanders in each run on its own: free {shared[0]}@run")
        for name in ("max_arc_steps", "max_iter", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} = {getattr(self, name)!r}: must be a positive integer")
        if self.multistart < 0:
            raise ValueError(f"multistart = {self.multistart!r}: must be >= 0")
        if self.auto_starts < 0:
            raise ValueError(f"auto_starts = {self.auto_starts!r}: must be >= 0")
        if self.sequence_trials < 0:
            raise ValueError(f"sequence_trials = {self.sequence_trials!r}: must be >= 0")
        passes = (self.sequence_passes,) if isinstance(self.sequence_passes, str) else tuple(self.sequence_passes)
        object.__setattr__(self, "sequence_passes", passes)
        unknown = [p for p in passes if p not in SEQUENCE_PASSES]
        if unknown:
            raise ValueError(f"sequence_passes: {', '.join(map(repr, unknown))} is not a pass; choose from "
                             f"{', '.join(SEQUENCE_PASSES)}")
        if self.arc_jacobian not in ("forward", "central", "exact"):
            raise ValueError(f"arc_jacobian = {self.arc_jacobian!r}: choose 'forward', 'central' or 'exact'")
        if self.arc_start not in ("aged", "mid"):
            raise ValueError(f"arc_start = {self.arc_start!r}: choose 'aged' or 'mid'")
        if self.trigger not in ("uniform", "interval"):
            raise ValueError(f"trigger = {self.trigger!r}: choose 'uniform' or 'interval'")
        if self.trigger == "interval" and self.arc_start != "aged":
            raise ValueError("trigger = 'interval' needs arc_start = 'aged': the interval bounds the arcs' "
                             "start positions, which arc_start = 'mid' does not have")
        if self.covariance not in ("robust", "cluster", "model"):
            raise ValueError(f"covariance = {self.covariance!r}: choose 'robust', 'cluster' or 'model'")
        if self.solver not in ("gauss-newton", "ipopt"):
            raise ValueError(f"solver = {self.solver!r}: choose 'ipopt' or 'gauss-newton'")
        for attr, cls in _NESTED.items():
            if not isinstance(getattr(self, attr), cls):
                raise ValueError(f"{attr} = {getattr(self, attr)!r}: must be a {cls.__name__}")
        if self.stick_speed not in ("check", "auto", "off"):
            raise ValueError(f"stick_speed = {self.stick_speed!r}: choose 'check', 'auto' or 'off'")


_NESTED = {"stop": StopOptions, "gauss_newton": GaussNewtonOptions, "ipopt": IpoptOptions}
# (evolve routes a field's name to the options that own it: the names must be unique)
assert len({n for names in SOLVER_FIELDS.values() for n in names}) == sum(map(len, SOLVER_FIELDS.values()))
