"""Fit time and peak memory vs N for every method (issue 13 item 7): ``python benchmarks/fit_time.py [--sizes …]``.

The logic lives in :mod:`labcal.bench.fit_time` so ``labcal bench fit-time`` runs the same code. Committed results:
benchmarks/results/fit_time_before.txt (before the issue-13 changes) and fit_time.txt (after).
"""

import sys

from labcal.bench.fit_time import main

if __name__ == "__main__":
    sys.exit(main())
