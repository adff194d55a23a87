"""The rough track withheld from the baseline: the diagnosis names ``topography_field``,
and the field it fits follows the track the data were made on (not its coefficients: the
data's track has a period the fit's series does not share)."""

import numpy as np
import pytest

import identify
from identify.model.effects import get_effect
from identify.model.symbolic import Model
from identify.simulation.withheld import CONDITIONS, withheld_dataset


@pytest.mark.slow
def test_a_rough_track_withheld_from_the_baseline_is_named_and_its_field_follows_the_truth():
    """Measured: named, adequate, held-out gap 85 -> 31 nm (noise 25 nm), 542 s on two cores."""
    conds = [CONDITIONS[i] for i in (2, 3, 5, 7)]  # 10 and 20 µN on 2.13 N/m, 30 and 60 µN on 20.3 N/m
    traces = withheld_dataset("topography_field", conditions=conds, base={"A": 0.015})
    fo = identify.FitOptions(fixed={"v_stick": 1e-5}, free=("mu_max", "mu_min", "tau", "A"))
    res = identify.diagnose(traces, fit_options=fo,
                            options=identify.DiagnosisOptions(workers=2, effects=("topography_field",)))
    assert res.effects == ["topography_field"]
    assert res.verdict == "adequate"
    rec = next(c for c in res.candidates if c["effect"] == "topography_field")
    assert rec["heldout_gap_after_um"] < 0.6 * rec["heldout_gap_before_um"]
    # the field along the positions every run crossed, its mean taken out (the friction
    # coefficients absorb a constant): within a tenth of the track's own spread (measured: 3 %)
    m = Model()
    x = np.linspace(0.5e-6, 25e-6, 200)
    truth = m.topography(x, {**m.defaults({}), **get_effect("topography_field").simulation_values()})
    fitted = m.topography(x, {**m.defaults({}), **res.final["values"]})
    truth, fitted = truth - truth.mean(), fitted - fitted.mean()
    assert np.sqrt(np.mean((fitted - truth) ** 2)) < np.std(truth) / 10
