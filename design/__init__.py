"""nanofrictor.design: springs, Table I constraints and spring-set design.

Modules
-------
springs
    k(w) of the folded fixed-guided suspension (Eq. (1)), :class:`Suspension`, the paper's
    springs, drawn/effective widths.
constraints
    Table I as named :class:`Constraint` objects; allowed Nb range of a spring.
spring_set
    The fewest springs covering a load range for every μ, robust to the etch bias
    (CasADi + Ipopt), judged side by side with the paper's set.
spring_coverage
    A spring set judged against a load range: margins, gaps, the pointwise Table I check.
spring_maximin
    The maximin NLP of one assignment of springs to suspensions (Ipopt).
spring_set_result
    The designed set beside the paper's, with its report and JSON.
ranges
    Operating ranges of a spring: the usable (Nb, fp) points under Table I, the simulated
    regime and the camera (:func:`operating_ranges`).
plots
    Fig. 3 (the Table I region) with spring sets drawn on it; operating-range maps.
experiment
    Experiment plans that make the friction parameters identifiable (D/A/E-optimal
    choice of runs).
candidates
    The runs a plan chooses from, and the paper's conditions as the reference plan.
information
    The Fisher information of one run, from the identification's own NLP.
experiment_plan
    A plan beside the reference, with its report, JSON and plot.
verification
    Monte Carlo fits of a plan and its reference: the measured spread of the estimates.
cli
    ``nanofrictor-design springs|ranges|experiment ...`` (or ``python -m design ...``).
"""

from identify import __version__

from .constraints import (
    TABLE_I,
    Constraint,
    ConstraintViolation,
    Sense,
    Violation,
    allowed_load_range,
    check,
    elongation_window,
    require,
    robust_load_range,
)
from .experiment import Candidate, ExperimentPlan, design_experiment, paper_plan, verify_plans
from .plots import plot_design, plot_feasible_region, plot_operating_ranges, plot_spring_set
from .ranges import OperatingRanges, UsabilityRules, operating_ranges
from .spring_set import (
    DEFAULT_SUSPENSIONS,
    MAX_SPRINGS,
    Attempt,
    InfeasibleDesignError,
    SpringSet,
    SpringSetResult,
    coverable_load_range,
    design_spring_set,
    paper_spring_set,
)
from .springs import (
    ETCH_BIAS_UM,
    LONG_SUSPENSION,
    PAPER_SPRING_CONSTANTS,
    PAPER_SUSPENSION,
    PAPER_WIDTHS_UM,
    SpringDesign,
    Suspension,
    drawn_width_um,
    effective_width_um,
    paper_springs,
    spring_constant,
    width_for_spring_constant,
)

__all__ = [
    "__version__",
    # springs
    "ETCH_BIAS_UM",
    "LONG_SUSPENSION",
    "PAPER_SPRING_CONSTANTS",
    "PAPER_SUSPENSION",
    "PAPER_WIDTHS_UM",
    "SpringDesign",
    "Suspension",
    "drawn_width_um",
    "effective_width_um",
    "paper_springs",
    "spring_constant",
    "width_for_spring_constant",
    # constraints
    "TABLE_I",
    "Constraint",
    "ConstraintViolation",
    "Sense",
    "Violation",
    "allowed_load_range",
    "check",
    "elongation_window",
    "require",
    "robust_load_range",
    # spring sets
    "DEFAULT_SUSPENSIONS",
    "MAX_SPRINGS",
    "Attempt",
    "InfeasibleDesignError",
    "SpringSet",
    "SpringSetResult",
    "coverable_load_range",
    "design_spring_set",
    "paper_spring_set",
    # operating ranges
    "OperatingRanges",
    "UsabilityRules",
    "operating_ranges",
    # experiment design
    "Candidate",
    "ExperimentPlan",
    "design_experiment",
    "paper_plan",
    "verify_plans",
    # plots
    "plot_design",
    "plot_feasible_region",
    "plot_operating_ranges",
    "plot_spring_set",
]
