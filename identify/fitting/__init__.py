"""The full-model fit: the multiple-shooting problem (layout, assembly, evaluation,
solvers, covariance), the slip arcs and their derivatives, the mode-sequence decisions,
the start, and the result."""
