"""The targets benchmark (issue 15.4): ``python benchmarks/targets.py [--seeds 3] [--quick] [--out F] [--plot P]``.

The logic lives in :mod:`labcal.bench.targets` so ``labcal bench targets`` runs the same code. The full run's output
is committed as benchmarks/results/targets.txt and its plot as benchmarks/results/targets.png:

    python benchmarks/targets.py --out benchmarks/results/targets.txt --plot benchmarks/results/targets.png
"""

import sys

from labcal.bench.targets import main

if __name__ == "__main__":
    sys.exit(main())
