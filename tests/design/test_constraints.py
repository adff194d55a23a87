"""Table I as constraint objects: allowed ranges, messages, vectorisation (MODEL.md)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from design import constraints as tc
from design.plots import plot_feasible_region


def test_coverage_of_2_13_N_per_m():
    # MODEL.md / paper: k = 2.13 N/m covers 1.92 µN to 237 µN.
    lo, hi = tc.allowed_load_range(2.13)
    assert lo * 1e6 == pytest.approx(1.92, abs=0.005)
    assert hi * 1e6 == pytest.approx(237, abs=0.5)
    assert hi / lo == pytest.approx(123.5, rel=1e-3)  # "a ratio of about 123"


def test_paper_worked_example():
    # Nb = 235 µN, k = 2.13, μ = 0.9 -> e ≈ 100 µm; Nb = 1.92 µN, μ = 0.1 -> e ≈ 0.09 µm.
    assert tc.PULLER_TRAVEL.value(235e-6, 2.13, 0.9) == pytest.approx(100e-6, rel=0.01)
    assert tc.ELONGATION_RESOLUTION.value(1.92e-6, 2.13, 0.1) == pytest.approx(90e-9, rel=0.01)


def test_allowed_range_is_clipped_by_the_load_rows_and_empty_outside_k_rows():
    lo, hi = tc.allowed_load_range(np.array([0.01, 20.3, 100.0, 0.005, 150.0]))
    assert lo[0] == pytest.approx(10e-9)  # k·90 nm/0.1 = 9 nN, raised to Table I's 10 nN
    assert hi[1] == pytest.approx(452e-6)  # 20.3·100 µm/0.9 = 2.26 mN, capped at 452 µN
    assert np.isfinite(lo[2])
    assert np.isnan(lo[3]) and np.isnan(hi[4])


def test_range_ends_pass_every_row_and_just_outside_fails():
    k = np.geomspace(0.02, 50, 9)
    lo, hi = tc.allowed_load_range(k)
    mu = np.linspace(0.1, 0.9, 17)
    for nb in (lo, hi, np.sqrt(lo * hi)):
        assert tc.satisfied(nb[:, None], k[:, None], mu[None, :]).all()
    assert not tc.satisfied(lo[:, None] * 0.999, k[:, None], mu[None, :]).all(axis=1).any()
    assert not tc.satisfied(hi[:, None] * 1.001, k[:, None], mu[None, :]).all(axis=1).any()


def test_violation_message_names_rule_and_point():
    with pytest.raises(tc.ConstraintViolation) as exc:
        tc.require(300e-6, 2.13, 0.9)
    msg = str(exc.value)
    assert msg.startswith("e < 100 µm violated at Nb = 300 µN, k = 2.13 N/m, μ = 0.9")
    assert "e = 127 µm" in msg
    assert isinstance(exc.value, ValueError)


def test_check_is_vectorised_and_reports_each_failing_point():
    nb = np.array([1e-9, 5e-6, 1e-3])
    v = tc.check(nb[:, None], 2.13, np.array([0.05, 0.5])[None, :])
    names = {x.constraint.name for x in v}
    assert names == {"e > 90 nm", "e < 100 µm", "Nb > 10 nN", "Nb < 452 µN", "μ > 0.1"}
    # μ = 0.05 fails at all three loads
    assert sum(x.constraint is tc.MU_MIN for x in v) == 3
    low = [x for x in v if x.constraint is tc.LOAD_MIN]
    assert len(low) == 2 and all(x.normal_load == 1e-9 for x in low)
    assert "Nb > 10 nN violated at Nb = 1 nN" in low[0].message
    ok = tc.satisfied(nb[:, None], 2.13, np.array([0.1, 0.9])[None, :])
    assert ok.shape == (3, 2)
    assert ok.tolist() == [[False, False], [True, True], [False, False]]


def test_k_rows():
    assert [x.constraint.name for x in tc.check(1e-6, 200.0, 0.5)][-1] == "k < 100 N/m"
    assert any(x.constraint is tc.K_MIN for x in tc.check(1e-8, 0.005, 0.5))


def test_table_i_objects():
    assert len(tc.TABLE_I) == 8
    assert len({c.name for c in tc.TABLE_I}) == 8
    assert all(c.reason for c in tc.TABLE_I)
    assert tc.ELONGATION_RESOLUTION.bound == 90e-9 and tc.LOAD_MAX.bound == 452e-6
    with pytest.raises(ValueError, match="quantity"):
        tc.Constraint("x > 1", "x", tc.Sense.GREATER, 1.0, "-", "", 1.0, "none")


def test_robust_range_uses_stiffest_floor_and_softest_ceiling():
    lo, hi = tc.robust_load_range(1.8, 2.5)
    assert lo == pytest.approx(2.5 * 90e-9 / 0.1)
    assert hi == pytest.approx(1.8 * 100e-6 / 0.9)
    assert np.isnan(tc.robust_load_range(0.009, 0.012)[0])  # softest breaks k > 0.01 N/m


def test_feasible_region_plot():
    fig = Figure()
    ax = plot_feasible_region(fig.add_subplot())
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    assert "N/m" in ax.get_xlabel() and "µN" in ax.get_ylabel()
