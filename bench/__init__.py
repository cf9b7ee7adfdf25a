"""Benchmarks: each prints the figures the docs quote. Shared here: the ``--set`` option."""
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
