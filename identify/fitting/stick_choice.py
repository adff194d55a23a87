"""Stick or creep, decided before the solver runs (issue: a runaway without the stick
option).

A recorded trace never says whether the block sticks at rest (the simulator's stick
option, ``v_stick`` > 0) or creeps (the equations as written, ``v_stick`` = 0). Under the
equations as written the model creeps at some conditions where real data stick-slip;
fitted there, the solver cannot make slips the model does not have and runs away
(measured on the bundled FOTAS set without the option: χ² 2e7 after 70 s, still
climbing). Simulating each stick-slip run once at the start values, both ways, takes
seconds and tells which option the data allow.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from identify.model.scopes import device_of, resolve

__all__ = ["STICK_SPEED_AUTO", "StickChoice", "stick_choice"]

log = logging.getLogger(__name__)

STICK_SPEED_AUTO = 1e-5  # m/s: the stick option the simulator and the bundled data use
# the share of stick-slip runs the model may creep in before the equations as written
# are judged unable to fit the data (one run of many can sit on the regime boundary at
# a start that is only near the truth)
MISMATCH_SHARE = 0.25
CHECK_STEPS = 600  # puller steps simulated per run: enough for a saw-tooth to show


@dataclass
class StickChoice:
    """What the check found: per option, the stick-slip runs the model creeps in."""

    n_stick_slip: int
    creeping: dict = field(default_factory=dict)  # v_stick -> names of runs the model creeps in
    chosen: float | None = None

    def mismatch(self, v_stick: float) -> bool:
        return self.n_stick_slip > 0 and len(self.creeping.get(v_stick, ())) >= MISMATCH_SHARE * self.n_stick_slip

    def text(self, v_stick: float = 0.0) -> str:
        names = self.creeping.get(v_stick, [])
        shown = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
        return f"{len(names)} of {self.n_stick_slip} runs whose data stick-slip ({shown})"


def stick_choice(runs_ev, model, values: dict, options=(0.0, STICK_SPEED_AUTO), say=None) -> StickChoice:
    """Simulate every stick-slip run of ``runs_ev`` (:class:`identify.traces.events.RunEvents`)
    at ``values`` under each stick option in ``options``; records where the model creeps.
    Stops at the first option that fits all runs' regime."""
    from identify.fitting.rundata import make_run_data
    from identify.simulation.hybrid import RunConditions, SimulationOptions, simulate_run

    runs = [(ev, make_run_data(ev)) for ev in runs_ev]
    runs = [(ev, rd) for ev, rd in runs if rd.kind == "events" and str(ev.regime) == "stick-slip"]
    out = StickChoice(n_stick_slip=len(runs))
    for v in options:
        creeping = []
        for _ev, rd in runs:
            steps = min(int(rd.trigger_steps[-1]) + 50 if len(rd.trigger_steps) else CHECK_STEPS, CHECK_STEPS)
            try:
                run_values = resolve(dict(values, v_stick=v), rd.name, device_of(rd))
                sim = simulate_run(model, run_values, RunConditions(rd.k, rd.Nb, rd.fp, steps),
                                   SimulationOptions(record=False))
            except Exception as err:  # noqa: BLE001 - a run the simulator cannot do says nothing here
                log.debug("stick check: %s at v_stick = %g not simulated: %s", rd.name, v, err)
                continue
            if sim.regime == "creep":
                creeping.append(rd.name)
        out.creeping[v] = creeping
        if say:
            say(f"stick check: v_stick = {v:g} m/s: the model creeps in {out.text(v)}" if creeping
                else f"stick check: v_stick = {v:g} m/s: the model stick-slips where the data do")
        if not out.mismatch(v):
            break
    return out
