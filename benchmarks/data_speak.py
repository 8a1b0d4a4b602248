"""Print the narrow-data table of issue 27 (labcal.bench.data_speak). Results: benchmarks/results/data_speak.txt.

python benchmarks/data_speak.py | tee benchmarks/results/data_speak.txt
"""

import sys

from labcal.bench.data_speak import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
