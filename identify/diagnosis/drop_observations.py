"""The frames around the slips as observations of the whole diagnosis, when motion blur is
one of its candidates (``FitOptions.drop_frames``).

A likelihood ratio compares two fits of the same observations: the blur candidate, which
reads the frames whose exposure straddles a slip, needs its null fitted to those frames
too, and so does every other candidate it is compared with. The baseline's runs are
rebuilt once, on the baseline's own mode sequence, with each slip's frames taken while
its block moved (the arcs' moving times at the baseline) left out: there the slip's
path, not the window, decides what a frame reads; a window reaching into the slip reads
it as a ramp over the time the slip covers its length in (``Problem.slip_ramps``). The
decision variables are the same, so the baseline's solution carries over; the current
model's record of the first round is its refit on these observations.
"""

from __future__ import annotations

import numpy as np

from identify.fitting.problem import Problem
from identify.fitting.rundata import make_run_data

__all__ = ["with_drop_observations"]


def with_drop_observations(prob, w: np.ndarray):
    """``prob`` rebuilt with its runs' frames around each slip observed one by one, and
    the runs; ``(prob, prob.runs)`` unchanged when it already observes them or has no
    slip."""
    if prob.D or not prob.E:
        return prob, prob.runs
    moving, ramps = prob.moving_times(w), prob.slip_ramps(w)
    runs = [make_run_data(r.events, triggers=r.trigger_steps, moving_s=moving.get(i), drops=True,
                          ramp_s=ramps.get(i))
            if r.kind == "events" else r for i, r in enumerate(prob.runs)]
    new = Problem(runs, prob.model, prob.values, prob.opts.evolve(drop_frames=True))
    new.ev_M = np.array(prob.ev_M)
    new.counter = prob.counter
    new.build()
    new.size_arcs(w)
    return new, runs
