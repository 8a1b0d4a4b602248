"""The robustness benchmark (issue 13 item 6): ``python benchmarks/robustness.py [--splits 5] [--quick] [--out F]``.

The logic lives in :mod:`labcal.bench.robustness` so ``labcal bench robustness`` runs the same code. Committed
results: benchmarks/results/robustness_before.txt (before the issue-13 changes) and robustness.txt (after).
"""

import sys

from labcal.bench.robustness import main

if __name__ == "__main__":
    sys.exit(main())
