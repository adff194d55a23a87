"""Speed/agreement benchmark of the hybrid simulator against the paper's smooth route.

A benchmark, not a timed test (pytest does not collect this file): it prints the
ratios measured in the same run and which of the issue's targets are met.

    python tests/bench/bench_simulator.py            # full: 6 cases, Radau + LSODA, ~10-30 min
    python tests/bench/bench_simulator.py --quick    # smoke test, ~1-2 min
    python tests/bench/bench_simulator.py --json out.json

Same as ``python -m identify bench``; see :mod:`identify.bench` for the design.
"""

import os
import sys

# "on one core": keep BLAS/OpenMP single-threaded (must be set before numpy is imported)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from identify.bench import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
