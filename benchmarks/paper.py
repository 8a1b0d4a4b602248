"""The paper benchmark (DESIGN.md section 6): ``python benchmarks/paper.py [--seeds 5] [--quick]``.

The logic lives in :mod:`labcal.bench.paper` so ``labcal bench paper`` runs the same code. A full run's output
is committed as benchmarks/results/paper.txt.
"""

import sys

from labcal.bench.paper import main

if __name__ == "__main__":
    sys.exit(main())
