"""`labcal bench speed`: the compensator speed benchmark (the table of benchmarks/compensator_speed.py)."""

from __future__ import annotations

import runpy
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Run benchmarks/compensator_speed.py from the source tree (it is not part of the installed package)."""
    script = Path(__file__).resolve().parents[3] / "benchmarks" / "compensator_speed.py"
    if not script.is_file():
        raise FileNotFoundError(f"{script} not found: `labcal bench speed` runs from a source checkout")
    module = runpy.run_path(str(script))
    module["main"](list(argv or []))
    return 0
