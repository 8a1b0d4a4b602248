"""Bad-input table (issue 12 acceptance): ``python benchmarks/bad_inputs.py [--cases …] [--out FILE]``.

Runs every bad-input case through the real CLI in temporary stores and prints case → where it was stopped →
message → exit code. The logic lives in :mod:`labcal.bench.bad_inputs` so ``labcal bench bad-inputs`` runs the same
code. Committed results: benchmarks/results/bad_inputs_before.txt and bad_inputs.txt.
"""

import sys

from labcal.bench.bad_inputs import main

if __name__ == "__main__":
    sys.exit(main())
