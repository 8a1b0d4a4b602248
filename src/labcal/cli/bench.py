"""`labcal bench …`: run the benchmarks (they print their tables)."""

from __future__ import annotations

import importlib

import typer

from labcal.cli.common import err

app = typer.Typer(
    help=(
        "Run the benchmarks; each prints its tables.\n\nExamples:\n\n  labcal bench paper -- --quick\n\n"
        "  labcal bench speed\n\n  labcal bench robustness --quick\n\n  labcal bench targets --quick"
    ),
    no_args_is_help=True,
)
PASS = {"allow_extra_args": True, "ignore_unknown_options": True}


def _run(module: str, args: list[str]) -> None:
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name != module:
            raise
        err.print(f"error: {module} is not available in this version of labcal yet", markup=False)
        raise typer.Exit(2) from None
    code = mod.main(list(args))
    raise typer.Exit(int(code or 0))


@app.command("paper", context_settings=PASS)
def paper(ctx: typer.Context) -> None:
    """The paper's Section V protocol on the simulator (extra arguments go to the benchmark, e.g. --quick)."""
    _run("labcal.bench.paper", ctx.args)


@app.command("real-ur10", context_settings=PASS)
def real_ur10(ctx: typer.Context) -> None:
    """Calibrate on the real UR10 data set and report held-out errors per method."""
    _run("labcal.bench.real_ur10", ctx.args)


@app.command("speed", context_settings=PASS)
def speed(ctx: typer.Context) -> None:
    """Compensator latency/throughput (extra arguments: --batch N, --repeats N, --robot NAME)."""
    _run("labcal.bench.speed_cli", ctx.args)


@app.command("robustness", context_settings=PASS)
def robustness(ctx: typer.Context) -> None:
    """Every method with default options on sweeps, paper A/B and real UR10 vs a plain LSQ (--quick, --splits N)."""
    _run("labcal.bench.robustness", ctx.args)


@app.command("targets", context_settings=PASS)
def targets(ctx: typer.Context) -> None:
    """Held-out point error vs targets per pose (1, 2, 3, 3 with 30 % missing) on paper A/B and real UR10 (--quick)."""
    _run("labcal.bench.targets", ctx.args)


@app.command("fit-time", context_settings=PASS)
def fit_time(ctx: typer.Context) -> None:
    """Fit wall time and peak memory vs N for every method (--sizes 50 1000 5000, --methods auto,hybrid)."""
    _run("labcal.bench.fit_time", ctx.args)


@app.command("bad-inputs", context_settings=PASS)
def bad_inputs(ctx: typer.Context) -> None:
    """Feed every bad-input case through import → fit → export and print where each was stopped (--cases …)."""
    _run("labcal.bench.bad_inputs", ctx.args)
