"""Bad-input table (issue 12 acceptance): ``python benchmarks/bad_inputs.py [--cases …] [--out FILE]``.

Runs every bad-input case through the real CLI in temporary stores and prints case → where it was stopped →
message → exit code. The cases, how each runs and its verdict live in tests/acceptance/bad_input_cases.py: the
acceptance suite tests/acceptance/test_bad_inputs.py fails on any verdict that is not ``ok``; this script prints
the same cases as one table. Committed results: benchmarks/results/bad_inputs_before.txt and bad_inputs.txt.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "acceptance"))
from bad_input_cases import CASES, run_case, verdict


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(r):
        return "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()

    return [line(header), "  ".join("-" * w for w in widths), *[line(r) for r in rows]]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bad-inputs", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--cases", nargs="+", help="run only these cases (default: all): " + ", ".join(c.name for c in CASES)
    )
    p.add_argument("--method", default="auto", help="fit method of the data cases (default auto, what a user gets)")
    p.add_argument("--local-method", default="local-poe", help="fit method of the setup of export/compensator cases")
    p.add_argument("--out", help="also write the table to this file")
    p.add_argument("--note", help="a line printed under the command (e.g. which commit was measured)")
    p.add_argument("--json", help="also write the raw outcomes as JSON here")
    args = p.parse_args(argv)
    cases = [c for c in CASES if not args.cases or c.name in args.cases]
    unknown = set(args.cases or ()) - {c.name for c in CASES}
    if unknown:
        p.error(f"unknown case(s) {sorted(unknown)}")
    out: list[str] = []

    def say(line: str = "") -> None:
        print(line, flush=True)
        out.append(line)

    say("bad-inputs: every mistake through the CLI (import → fit → export, no --force unless the case says so)")
    say(f"command: python benchmarks/bad_inputs.py {' '.join(argv if argv is not None else sys.argv[1:])}".rstrip())
    if args.note:
        say(f"note: {args.note}")
    rows, raw = [], []
    started = time.perf_counter()
    for case in cases:
        t = time.perf_counter()
        o = run_case(case, args)
        v = verdict(case, o)
        code = "-" if o.code is None else str(o.code)
        rows.append([case.name, case.expect, o.stage, code, "yes" if o.traceback else "", v, o.message])
        raw.append({"case": case.name, "what": case.what, "expect": case.expect, "stage": o.stage, "code": o.code,
                    "traceback": o.traceback, "verdict": v, "message": o.message})  # fmt: skip
        print(f"  {case.name}: {o.stage} (exit {code}, {time.perf_counter() - t:.0f} s) {o.message}", flush=True)
    say("")
    for line in _table(["case", "expect", "stopped at", "exit", "traceback", "verdict", "message (first line)"], rows):
        say(line)
    say("")
    for c in cases:
        say(f"  {c.name}: {c.what}")
    counts = {v: sum(r[5] == v for r in rows) for v in ("ok", "FAIL", "open", "traceback", "-")}
    stopped = sum(r[2] != "NOT stopped" for r in rows)
    say("")
    say(
        f"{len(rows)} cases: {stopped} stopped; verdicts ok {counts['ok']}, FAIL {counts['FAIL']}, "
        f"open {counts['open']}, traceback {counts['traceback']}, info {counts['-']} "
        f"({time.perf_counter() - started:.0f} s)"
    )
    must = [r for r in rows if r[1] == "must-stop"]
    say(
        f"issue 12 independent check: must-stop cases stopped {sum(r[5] == 'ok' for r in must)}/{len(must)}; "
        "good file through untouched: "
        + next((("yes" if r[5] == "ok" else "NO") for r in rows if r[0] == "good"), "not run")
    )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text("\n".join(out) + "\n")
    if args.json:
        Path(args.json).write_text(json.dumps(raw, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
