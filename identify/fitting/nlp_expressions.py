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
from identify.model.params import topo_field_names
from identify.model.scopes import parse
from identify.model.symbolic import LENGTH_UNIT

__all__ = ["NLPExpressions"]


class NLPExpressions:
    """The NLP's expressions and Functions (mixed into the problem, whose layout they read)."""

    def _camera_terms(self, P, step):
        """What the camera adds to each plateau's mean elongation (m).

        Drift: + drift_rate·t̄_p (t̄_p the plateau's mean frame time).
        Motion blur: a frame at step phase u (fraction of the step interval since the
        last step) averaging e over an exposure T centred on it reads, with h = T·fp/2
        (T·fp ≤ 1),  e(t) + Δx·[max(0, u + h − 1) − max(0, h − u)]/(2h): a part of the
        next step when the window reaches it, minus a part of the current one when the
        window starts before it. Frames placed symmetrically in the step interval (the
        usual two frames per step at u = ¼, ¾) cancel in the plateau mean: the blur then
        shows only in frames taken during a slip, which the plateaus leave out.
        """
        out = ca.DM.zeros(self.P, 1)
        if "drift_rate" in self.scoped_bases:  # a rate per run
            out = out + self.per_run_column(P, "drift_rate", self.pl_run) * ca.DM(self.pl_mean_t)
        elif "drift_rate" in self.theta.names or self.values.get("drift_rate", 0.0) != 0.0:
            out = out + P["drift_rate"] * ca.DM(self.pl_mean_t)
        if "exposure" in self.theta.names or self.values.get("exposure", 0.0) != 0.0:
            rows = []
            for r in self.runs:
                if r.kind != "events":
                    continue
                u = ca.DM(r.frame_phases).T  # 1 × U
                h = P["exposure"] * r.fp / 2
                b = (ca.fmax(0, u + h - 1) - ca.fmax(0, h - u)) / (2 * h + 1e-30)
                counts = ca.DM(r.phase_counts)  # plateaus × U
                rows.append(ca.mtimes(counts, b.T) / ca.DM(np.maximum(r.plateau_n, 1)))
            out = out + step * ca.vertcat(*rows)
        return out

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
        for ri, r in enumerate(self.runs):
            if r.kind == "events" and r.s_nn > 0:
                # a drift adds drift/fp per step to the staircase slope
                res.append(math.sqrt(r.s_nn) * (step + drift[ri] / r.fp - r.slope_hat) / r.sigma)
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
