"""Benchmarks: each prints the figures the docs quote. Shared here: the ``--set`` option, the
evaluation with a patched planner (``patched_eval_parser``, ``run_patched_eval``)."""
from __future__ import annotations

import argparse


def add_set_option(ap: argparse.ArgumentParser, example: str = "tracking.plan_steering=true") -> None:
    """``--set KEY=VALUE`` (repeatable): a scenario value changed for this run, VALUE read as YAML."""
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help=f"change a scenario value, e.g. {example}")


def set_overrides(ap: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """The ``--set`` items as ``load_scenario`` overrides; a bad item exits 2 naming it."""
    from onboard.config import ConfigError, parse_overrides

    try:
        return parse_overrides(args.set)
    except ConfigError as exc:
        ap.error(str(exc))


def set_label(args: argparse.Namespace) -> str:
    """The run's ``--set`` items as they were given, for the benches' headings."""
    return "".join(f" --set {x}" for x in args.set)


def patched_eval_parser(doc: str, methods_help: str) -> argparse.ArgumentParser:
    """The options of a bench that runs ``pmon eval paper`` with its planner patched
    (bench/oracle_routes.py, route_variants.py): --out, --trials, --seed, --methods, --workers,
    --set; the bench adds its own."""
    from onboard.argcheck import SEED, integer

    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="directory for pmon eval's files")
    ap.add_argument("--trials", type=integer(1, 100_000), default=100)
    ap.add_argument("--seed", type=SEED, default=2024)
    ap.add_argument("--methods", default="flight@stock", help=methods_help)
    ap.add_argument("--workers", type=integer(1, 1024), default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="as pmon eval's --set")
    return ap


def run_patched_eval(a: argparse.Namespace) -> int:
    """``pmon eval paper`` with the options of ``patched_eval_parser`` (no figures, quiet)."""
    from onboard.cli import main as pmon

    extra = [x for kv in a.set for x in ("--set", kv)]
    return pmon(["eval", "paper", "--trials", str(a.trials), "--seed", str(a.seed), "--methods", a.methods,
                 "--workers", str(a.workers), "--no-figures", "--quiet", "--out", a.out, *extra])
