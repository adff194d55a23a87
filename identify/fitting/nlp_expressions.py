"""The identification NLP as CasADi expressions (:mod:`identify.fitting.problem` states
it): residuals, continuity constraints and the arcs' inputs in the decision variables,
and the Functions built from them, the arcs' Jacobians chain-ruled in. :class:`NLPExpressions`
is mixed into :class:`identify.fitting.problem.Problem`.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from identify.fitting.arc_callback import ArcCallback, blockdiag_sparsity
from identify.fitting.mode_sequence.triggers import START_SCALE_UM
from identify.model.params import topo_field_names, walk_names
from identify.model.scopes import parse
from identify.model.symbolic import LENGTH_UNIT

__all__ = ["NLPExpressions", "staircase_blur", "BLUR_STEPS"]

BLUR_STEPS = 3
"""Puller steps on each side of a frame an exposure window may reach (T·fp up to 3)."""


def staircase_blur(u, H, a):
    """n̄ − n: how far the puller's staircase averaged over a frame's exposure lies above
    its count at the timestamp, in steps.

    A frame at step phase ``u`` (fraction of the step interval since the last step)
    averages over [u − a·H, u + (1 − a)·H] in step units, ``H`` = T·fp the exposure in
    step periods and ``a`` the share of it before the timestamp (``exposure_align``):
    the window's share past each later step m ≥ 1, less its share before each step
    m ≤ 0 it starts before. Element-wise over ``u`` (and ``H``); at H = 0 the steps
    between the timestamp and the count's own, floor(u) (0 for a phase in [0, 1)).
    """
    Hs = H + 1e-30
    out = 0
    for m in range(BLUR_STEPS):
        out = out + ca.fmin(ca.fmax((u + (1 - a) * H - (m + 1)) / Hs, 0), 1) \
                  - ca.fmin(ca.fmax((a * H - u - m) / Hs, 0), 1)
    return out


class NLPExpressions:
    """The NLP's expressions and Functions (mixed into the problem, whose layout they read)."""

    def _blurred(self) -> bool:
        return "exposure" in self.theta.names or self.values.get("exposure", 0.0) != 0.0

    def _walk_modes(self) -> list:
        """The random walk's modes in play: (m, name) of those free or not zero."""
        return [(m, n) for m, n in enumerate(walk_names(), start=1)
                if n in self.scoped_bases or n in self.theta.names or self.values.get(n, 0.0) != 0.0]

    def _drift_at(self, P, runs: np.ndarray, t: np.ndarray):
        """The camera's drift at times ``t`` (s) of rows of ``runs`` (m; 0 without one):
        the rate's line, and the random walk of its zero as the series
        Σₘ walk_m·√2·sin((m − ½)π·t/T) over the run's span T (a Wiener process's
        Karhunen–Loève modes; :class:`identify.model.effects.DriftWalk`)."""
        if "drift_rate" in self.scoped_bases:  # a rate per run
            out = self.per_run_column(P, "drift_rate", runs) * ca.DM(t)
        elif "drift_rate" in self.theta.names or self.values.get("drift_rate", 0.0) != 0.0:
            out = P["drift_rate"] * ca.DM(t)
        else:
            out = ca.DM.zeros(len(t), 1)
        modes = self._walk_modes()
        if modes:
            s = np.asarray(t, float) / self.run_span[np.asarray(runs, int)]
            for m, n in modes:
                out = out + self.per_run_column(P, n, runs) * ca.DM(math.sqrt(2) * np.sin((m - 0.5) * math.pi * s))
        return out

    def _walk_slope(self, P) -> list:
        """Per run, the random walk's mean slope over the run (m/s): its value at the run's
        end over the span (it starts at 0), what it adds to the within-plateau slope."""
        modes = self._walk_modes()
        out = [0.0] * len(self.runs)
        for m, n in modes:
            end = math.sqrt(2) * (-1) ** (m + 1)  # √2·sin((m − ½)π)
            out = [o + v * end / span for o, v, span in zip(out, self.per_run(P, n), self.run_span)]
        return out

    def _camera_terms(self, P, step):
        """What the camera adds to each plateau's mean elongation (m).

        Drift: + drift_rate·t̄_p (t̄_p the plateau's mean frame time).
        Motion blur: a frame averages e over an exposure T placed on its timestamp by
        ``exposure_align`` (:func:`staircase_blur`); on a plateau the puller's staircase
        is all that moves. Frames placed symmetrically in the step interval (the usual
        two frames per step at u = ¼, ¾) cancel in a centred exposure's plateau mean: the
        blur then shows only in frames taken around a slip, which the plateaus leave out
        and ``FitOptions.drop_frames`` observes (:meth:`_drop_residuals`).
        """
        out = self._drift_at(P, self.pl_run, self.pl_mean_t)
        if self._blurred():
            rows = []
            for r in self.runs:
                if r.kind != "events":
                    continue
                b = staircase_blur(ca.DM(r.frame_phases).T, P["exposure"] * r.fp, P["exposure_align"])  # 1 × U
                counts = ca.DM(r.phase_counts)  # plateaus × U
                rows.append(ca.mtimes(counts, b.T) / ca.DM(np.maximum(r.plateau_n, 1)))
            out = out + step * ca.vertcat(*rows)
        return out

    def _drop_residuals(self, w, P, step):
        """Residuals of the frames around the slips (``FitOptions.drop_frames``), each in
        its noise units: the elongation Δx·n(t) − x(t) averaged over the frame's exposure,
        n(t) the puller's staircase and x(t) the block moving from its plateau before the
        slip to the one after along a ramp over the time the slip covers its length in
        (``RunData.drop_moving``, from the arcs at the mode sequence's last decision; 0
        before they were integrated). Without blur a frame reads the level on its side of
        the slip; with it, the share of its window on each side.
        Where the steps fall is the step phase estimated from the frames, moved by
        ``clock_shift`` (per run, ``clock_shift@run``): a blurred exposure moves that
        estimate, and a shift of the clock is the same as a shift of the window
        (``exposure_align``), so only one of the two can be free.
        """
        x_um = w[self.i_x : self.i_x + self.P]
        pre = self.ev_prev[self.dr_ev]
        x_pre = x_um[pre.tolist()] * LENGTH_UNIT
        x_post = x_um[(pre + 1).tolist()] * LENGTH_UNIT
        T = P["exposure"] if self._blurred() else 0.0
        a = P["exposure_align"]
        Te = ca.fmax(T, 1e-9)  # (guards the division in the branch not taken)
        D = ca.DM(np.maximum(self.dr_moving, 1e-9))
        # the steps (and the slip) δ later than the estimated step phase puts them
        if "clock_shift" in self.scoped_bases:
            shift = self.per_run_column(P, "clock_shift", self.dr_run)
        else:
            shift = P["clock_shift"]
        dt = ca.DM(self.dr_dt) - shift
        u = ca.DM(self.dr_phase) - shift * ca.DM(self.dr_fp)

        def ramp_integral(tau):  # ∫ clip(τ'/D, 0, 1) dτ' from −∞ to τ
            y = ca.fmin(ca.fmax(tau, 0), D)
            return y * y / (2 * D) + ca.fmax(tau - D, 0)

        # (at T = 0 the instant itself: a frame at the trigger step reads the block before it moves)
        share_after = ca.if_else(T > 0, (ramp_integral(dt + (1 - a) * Te) - ramp_integral(dt - a * Te)) / Te,
                                 ca.fmin(ca.fmax(dt / D, 0), 1))
        n_avg = ca.DM(self.dr_steps) + staircase_blur(u, T * ca.DM(self.dr_fp), a)
        model_e = step * n_avg - (x_pre + (x_post - x_pre) * share_after)
        if self.n_off:
            model_e = model_e + w[(self.i_off + self.dr_run).tolist()] * LENGTH_UNIT
        model_e = model_e + self._drift_at(P, self.dr_run, self.dr_t)
        return (ca.DM(self.dr_e) - model_e) / ca.DM(self.dr_sigma)

    # ---------------------------------------------------------------- symbolic NLP
    def _symbolic(self, w, Y):
        """Arc inputs A(w), residuals r(w, Y), constraints g(w, Y); Y = (slip, end state)."""
        th = w[: self.n_theta]
        P = self.params(th)
        E = self.E
        x_um = w[self.i_x : self.i_x + self.P]
        step = self.model.step(P)
        res = []
        if self.P:
            off = w[self.i_off + self.pl_run] if self.n_off else 0.0
            model_e = step * ca.DM(self.pl_mean_s) - x_um * LENGTH_UNIT + off * LENGTH_UNIT
            model_e = model_e + self._camera_terms(P, step)
            res.append(ca.sqrt(ca.DM(self.pl_n)) * (ca.DM(self.pl_mean_e) - model_e) / ca.DM(self.pl_sigma))
        drift = self.per_run(P, "drift_rate")
        walk = self._walk_slope(P)
        for ri, r in enumerate(self.runs):
            if r.kind == "events" and r.s_nn > 0:
                # a drift adds drift/fp per step to the staircase slope
                res.append(math.sqrt(r.s_nn) * (step + (drift[ri] + walk[ri]) / r.fp - r.slope_hat) / r.sigma)
        A, g = None, ca.MX(0, 1)
        if E:
            x_prev = x_um[self.ev_prev] * LENGTH_UNIT
            e0 = step * ca.DM(self.ev_step) - x_prev
            Pev = self.event_params(P, ops=ca)
            z0 = self.start_state(self.start_positions(w), x_prev, e0, Pev, ops=ca)
            rows = [(x_prev / LENGTH_UNIT).T, (e0 / LENGTH_UNIT).T, z0.T]
            for n in self.arcs.param_names:
                if n in self.scoped_bases:
                    rows.append(ca.reshape(Pev[n], 1, -1))
                else:
                    v = P[n]
                    rows.append(ca.repmat(v if isinstance(v, ca.MX) else ca.MX(v), 1, E))
            rows += [ca.DM(self.ev_k).T, ca.DM(self.ev_Nb).T, ca.DM(self.ev_fp).T, ca.DM(self.ev_M).T]
            A = ca.vertcat(*rows)
            # triggers: the previous arc's end state aged over the rest, in this interval
            nx = self.ev_next
            pv = nx - 1
            rest = (self.ev_step[nx] - self.ev_step[pv] - self.ev_M[pv]) / self.ev_fp[pv]
            z_aged = self.law.rest(Y[1, pv].T, ca.DM(rest), P, ops=ca)
            z_before = self.law.rest(Y[1, pv].T, ca.DM(np.maximum(rest - 1 / self.ev_fp[nx], 0)), P, ops=ca)
            Pn = self.event_params(P, nx, ops=ca)
            s_pos = self.position(z_aged, x_prev[nx], e0[nx], Pn, ops=ca, z_before=z_before)
            if not self.interval_triggers:
                phi = w[self.i_phi : self.i_phi + self.n_phase]
                k_of = np.array([self.phase_of_run[int(ri)] for ri in self.ev_run[nx]], int)
                # (a 1x1 MX indexed by a list comes back as a row: force a column)
                res.append(math.sqrt(12) * (s_pos - ca.reshape(phi[k_of.tolist()], -1, 1)))
                res.append(math.sqrt(12) * (phi - 0.5))
            g = x_um[self.ev_prev + 1] - x_um[self.ev_prev] - Y[0, :].T
            if self.n_s:
                # shooting: each arc starts where the previous arc's end, aged over the
                # rest, puts the capacity in the (plain) trigger interval; a run's first
                # slip from an unobserved initial contact, uniform over the interval
                self._s_target = self.position(z_aged, x_prev[nx], e0[nx], Pn, ops=ca)
                s_all = w[self.i_s : self.i_s + self.n_s]
                # (scaled to µm of slip length, so that the feasibility tolerance means
                # the same as for the slip lengths; a 1x1 MX indexed by a list comes back
                # as a row: force columns)
                s_next = ca.reshape(s_all[self.ev_next.tolist()], -1, 1)
                g = ca.vertcat(g, START_SCALE_UM * (s_next - ca.reshape(self._s_target, -1, 1)))
                if not self.interval_triggers:
                    res.append(math.sqrt(12) * (ca.reshape(s_all[self.ev_firsts.tolist()], -1, 1) - 0.5))
        for ri, r in enumerate(self.runs):
            if r.kind != "creep":
                continue
            Pr = self.run_params(P, ri)
            vp = r.fp * step
            zss = self.law.steady_state(vp, Pr, ops=ca)
            mu = self.law.static_coefficient(zss, Pr, ops=ca) + P["A"] * ca.log(1 + vp / P["vc"])
            f = self.model.spring_force(r.steady_mean_e, Pr, ops=ca)
            res.append((f - mu * self.model.normal_load(Pr)) / (r.k * r.steady_se))
        if self.D:
            res.append(self._drop_residuals(w, P, step))
        for n, sd in self.prior_sd().items():
            res.append(P[n] / sd)  # a zero-mean Gaussian prior (FitOptions.priors), last
        return A, ca.vertcat(*res), g

    def build(self):
        """Residual, constraint and derivative Functions (and Ipopt, when chosen)."""
        opts = self.opts
        E = self.E
        w = ca.MX.sym("w", self.n_w)
        Ysym = ca.MX.sym("Y", 2, max(E, 1))
        A, rY, gY = self._symbolic(w, Ysym)
        R_w = ca.jacobian(rY, w)
        if self.n_s:
            self._s_target_fun = ca.Function("s_target", [w, Ysym], [self._s_target])
        if E:
            ix = self.arcs.index
            # the block position matters to an arc only through the topography ripple:
            # without it, two fewer integrations per arc and Jacobian
            topo = any(n in self.theta.names or self.values.get(n, 0.0) != 0.0
                       for n in ("topo_amp", *topo_field_names()))
            rows = ([ix["x0_um"]] if topo else []) + [ix["e0_um"], ix["state0"]] \
                + [ix[n] for n in dict.fromkeys(parse(m)[0] for m in self.theta.names) if n in ix]
            self._cb_jac = ArcCallback("arc_jacs", self.arcs, E, opts.threads, True, self.counter, rows,
                                        scheme=opts.arc_jacobian)
            self._cb_val = ArcCallback("arcs", self.arcs, E, opts.threads, False, self.counter,
                                        jac_callback=self._cb_jac)
            Y = self._cb_val(A)[:2, :]
            JA = ca.MX(blockdiag_sparsity(2, self.arcs.n_in, E), ca.vec(self._cb_jac(A)))
            dY_dw = ca.mtimes(JA, ca.jacobian(ca.vec(A), w))
            r = ca.substitute(rY, Ysym, Y)
            g = ca.substitute(gY, Ysym, Y)
            Jr = ca.substitute(R_w + ca.mtimes(ca.jacobian(rY, ca.vec(Ysym)), dY_dw), Ysym, Y)
            Jg = ca.substitute(ca.jacobian(gY, w) + ca.mtimes(ca.jacobian(gY, ca.vec(Ysym)), dY_dw), Ysym, Y)
            self._arc_inputs = ca.Function("arc_inputs", [w], [A])
        else:
            r, g, Jr, Jg = rY, gY, R_w, ca.MX(0, self.n_w)
            self._arc_inputs = None
        self._r_fun = ca.Function("r", [w], [r])
        self._g_fun = ca.Function("g", [w], [g])
        self._jr_fun = ca.Function("Jr", [w], [Jr])
        self._jg_fun = ca.Function("Jg", [w], [Jg])
        self.n_g = int(g.numel())
        self.n_r = int(r.numel())
        if opts.solver == "ipopt":
            self._build_ipopt(w, r, g, Jr, Jg, opts)
        return self
