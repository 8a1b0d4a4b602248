"""The real-UR10 benchmark (DESIGN.md section 6): ``python benchmarks/real_ur10.py [--quick] [--sizes …] [--seeds …]``.

The logic lives in :mod:`labcal.bench.real_ur10` so ``labcal bench real-ur10`` runs the same code. The full run's
output is committed as benchmarks/results/real_ur10.txt and its plot as
benchmarks/results/real_ur10_learning_curve.png:

    python benchmarks/real_ur10.py --out benchmarks/results/real_ur10.txt \
        --plot benchmarks/results/real_ur10_learning_curve.png
"""

import sys

from labcal.bench.real_ur10 import main

if __name__ == "__main__":
    sys.exit(main())
