"""Spring-set optimisation: coverage at the worst-case bias, fewest springs, margins."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from matplotlib.figure import Figure

from design import constraints as tc
from design.spring_set import (
    InfeasibleDesignError,
    SpringSet,
    coverable_load_range,
    design_spring_set,
    paper_spring_set,
)
from design.springs import PAPER_SPRING_CONSTANTS, SpringDesign

MU = np.linspace(0.1, 0.9, 9)


@pytest.fixture(scope="module")
def default():
    return design_spring_set()


@pytest.fixture(scope="module")
def decade():
    return design_spring_set((0.1, 452.0), etch_bias_um=0.1)


def assert_robust_cover(result):
    """Every Table I row at both bias extremes, and the union covers the range."""
    s = result.spring_set
    b = s.etch_bias_um
    L_lo, L_hi = s.load_range
    lo, hi = s.load_ranges
    assert np.all(np.isfinite(lo))
    for i, spring in enumerate(s.springs):
        loads = np.geomspace(lo[i], hi[i], 60)
        for sign in (-1, +1):  # bias error −b and +b per edge
            k = spring.suspension.spring_constant(spring.width_um + sign * 2 * b)
            assert tc.check(loads[:, None], k, MU[None, :]) == [], (i, sign)
    grid = np.geomspace(L_lo, L_hi, 2000)
    g = grid[:, None]
    inside = (g >= lo[None, :] * (1 - 1e-12)) & (g <= hi[None, :] * (1 + 1e-12))
    assert inside.any(axis=1).all()
    assert s.covers and s.verify() == []


def test_default_design_covers_at_worst_case_bias(default):
    assert_robust_cover(default)
    assert default.worst_margin >= 0


def test_default_is_fewest_springs(default):
    n = default.spring_set.n
    assert n == 3
    assert [a.n for a in default.attempts] == [1, 2, 3]
    assert all(not a.covers and a.worst_margin < 0 for a in default.attempts[:-1])
    lo_uN, hi_uN = (x * 1e6 for x in default.load_range)
    with pytest.raises(InfeasibleDesignError, match=f"no set of {n - 1} springs covers"):
        design_spring_set((lo_uN, hi_uN), n_springs=n - 1)


def test_default_range_is_table_i_clipped_to_what_the_process_reaches(default):
    (reach_lo, reach_hi), _ = coverable_load_range()
    assert default.requested_load_range_uN is None
    assert default.load_range[1] == pytest.approx(tc.LOAD_MAX.bound)
    assert reach_lo <= default.load_range[0] <= reach_lo * 1.01
    assert any("10 nN" in n for n in default.notes)
    # 10 nN needs k_stiff <= 0.0111 and k_soft >= 0.01 N/m: (w+0.2)/(w-0.2) <= 1.111^(1/3)
    assert reach_lo > tc.LOAD_MIN.bound


def test_pinned_end_and_balanced_margins(default):
    m = default.spring_set.margins
    # the low end sits at the reachable limit; the other margins are balanced (maximin)
    assert 0 <= m[0] < 0.01
    np.testing.assert_allclose(m[1:], m[1:].max(), atol=1e-5)
    assert m[1] > 0.5


@pytest.mark.parametrize("bias", [0.0, 0.1])
def test_explicit_range_covered_both_bias_extremes(bias):
    r = design_spring_set((0.1, 452.0), etch_bias_um=bias)
    assert_robust_cover(r)
    with pytest.raises(InfeasibleDesignError):
        design_spring_set((0.1, 452.0), etch_bias_um=bias, n_springs=r.spring_set.n - 1)


def test_more_bias_never_helps(decade):
    r0 = design_spring_set((0.1, 452.0), etch_bias_um=0.0)
    assert r0.spring_set.n == decade.spring_set.n == 2
    assert r0.worst_margin > decade.worst_margin > 0


def test_single_spring_margins_balanced():
    r = design_spring_set((1.0, 50.0), n_springs=1)
    m = r.spring_set.margins
    assert m[0] == pytest.approx(m[1], abs=1e-6)
    # closed form on one suspension: ln(L_lo/k_stiff/9e-7) = ln(k_soft·1.111e-4/L_hi)
    assert_robust_cover(r)


def test_paper_set_under_the_same_measures(default):
    ref = default.reference
    np.testing.assert_allclose(ref.spring_constants, PAPER_SPRING_CONSTANTS)
    assert ref.gaps == []  # the paper's springs overlap at ±0.1 µm ...
    assert np.all(ref.margins[1:-1] > 1.5)
    assert not ref.covers  # ... but its 0.028 N/m spring does not reach down to 27.6 nN
    assert ref.covered_load_range[0] * 1e6 == pytest.approx(0.0355, rel=0.01)
    assert ref.uncovered[0][0] == pytest.approx(default.load_range[0])
    # nominal (no bias) paper ranges: 2.13 N/m covers 1.92-237 µN
    nominal = paper_spring_set((1e-7, 4e-4), etch_bias_um=0.0)
    assert nominal.load_ranges[0][2] * 1e6 == pytest.approx(1.92, abs=0.005)
    assert nominal.covers


def test_gap_is_reported():
    s = SpringSet((SpringDesign(2.0), SpringDesign(9.0)), (1e-7, 4e-4), 0.1)
    assert s.margins[1] < 0 and len(s.gaps) == 1 and not s.covers
    assert s.verify() and "allowed by no spring" in s.verify()[0]


@pytest.mark.parametrize(
    "load_range_uN, match",
    [
        (
            (0.001, 1000.0),
            r"no set of up to 8 springs covers 0.001-1000 µN: "
            r"Table I allows Nb in \[10 nN, 452 µN\]",
        ),
        ((0.01, 452.0), "lowest load any allowed spring resolves"),
        ((5.0, 1.0), "0 < low < high"),
        (("a", 1.0), "two numbers"),
    ],
)
def test_bad_load_ranges(load_range_uN, match):
    with pytest.raises(ValueError, match=match):
        design_spring_set(load_range_uN)


def test_too_much_bias_for_the_springs_available():
    with pytest.raises(InfeasibleDesignError, match="no set of up to 2 springs"):
        design_spring_set((0.05, 452.0), max_springs=2)
    with pytest.raises(ValueError, match="etch_bias_um"):
        design_spring_set(etch_bias_um=-0.1)
    with pytest.raises(ValueError, match="n_springs"):
        design_spring_set(n_springs=0)


def test_result_outputs(default):
    d = default.to_json()
    for key in ("springs", "covered_load_range_uN", "worst_margin", "reference", "etch_bias_um",
                "load_range_uN"):
        assert key in d
    assert set(d["reference"]) >= {"springs", "covered_load_range_uN", "worst_margin"}
    for sp in d["springs"] + d["reference"]["springs"]:
        assert set(sp) >= {"width_um", "spring_constant_N_per_m", "normal_load_range_uN"}
        assert len(sp["normal_load_range_uN"]) == 2
    json.dumps(d, allow_nan=False)
    assert d["etch_bias_um"] == 0.1 and d["load_range_uN"][1] == pytest.approx(452.0)
    text = default.report()
    assert "Paper's springs" in text and "worst margin" in text and "3 springs" in text
    ax = default.plot(ax=Figure().add_subplot())
    assert ax.get_xscale() == "log" and "µN" in ax.get_ylabel()


def test_multistart_agrees(decade):
    # each subproblem is convex: every start reaches the same optimum
    assert decade.n_best_found >= 2
    assert math.isfinite(decade.worst_margin)
