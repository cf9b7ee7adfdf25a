"""``pmon``: the Passive Monitor command line.

    pmon run ...                 the onboard app: the companion computer's program
    pmon check-config [FILE]     validate a scenario (default: the built-in paper scenario), with
                                 --set KEY=VALUE changes; names each experimental setting changed
    pmon replay RUNLOG           re-run a flight's run log through the core, to the same decisions
                                 (onboard/app/replay.py); --set KEY=VALUE: what-if
    pmon VERB ...                a verb another package declares in the entry-point group
                                 ``pmon.verbs`` (pyproject.toml): the simulator's demo, simulate,
                                 eval and feed (sim/verbs.py), the ground station's gcs

This module imports onboard/ alone, and a verb's module only when that verb runs (or ``pmon
--help`` lists them): ``pmon run`` loads no simulator, ground station, matplotlib or dask, which
a flight install (``pip install passive-monitor``, no extras) does not have. An entry point names
the extra its verb needs (``demo = "sim.verbs:demo [sim]"``); where that extra's packages are not
installed the verb is refused in one line saying which extra to install (exit 2).
"""
from __future__ import annotations

import re
import sys

from onboard.argcheck import OneLineParser, Version

VERBS = "pmon.verbs"  # the entry-point group: NAME = "module:main [extra]", main(argv) -> exit code
OWN = ("run", "check-config", "replay")


def _check(args) -> int:
    from onboard.config import ConfigError, load_scenario, parse_overrides

    try:
        sc = load_scenario(args.scenario, parse_overrides(args.set))
    except ConfigError as exc:
        print(f"pmon: {exc}", file=sys.stderr)
        return 2
    print(f"{sc.source}: ok: {len(sc.targets)} targets, {len(sc.obstacles)} obstacles, "
          f"{len(sc.goals)} goal region(s), horizon T={sc.guidance.horizon}, "
          f"{sc.tracking.particles} particles/target")
    for line in intent_lines(sc) + experimental_lines(sc):
        print(line)
    return 0


def experimental_lines(sc) -> list[str]:
    """One line per experimental setting the file or ``--set`` holds at other than its default:
    a research knob, not an error (docs/SETTINGS.md "Experimental settings")."""
    from onboard.settings.sections import experimental_changes

    return [f"{key}: experimental, {value} here (default {default}): a research knob, unsupported in flight"
            for key, value, default in experimental_changes(sc)]


def intent_lines(sc) -> list[str]:
    """What the flight policy's filter assumes of each target (docs/TRACKING.md "Intent"), and what
    the paper's does, in one line per target."""
    from onboard.core.monitor_setup import target_intents
    from onboard.policy import DEFAULT, with_policy

    flying = with_policy(sc, DEFAULT)
    if not flying.tracking.intent:
        return ["the flight policy's filter here has no motion modes (tracking.intent false): each target "
                "heads for its goal, or stays at its start without one"]
    out = []
    for t, it in zip(sc.targets, target_intents(flying)):
        goals = ", ".join(f"{n} {p:.2f}" for n, p in zip(it.names, it.prior))
        rest = f"stationary {it.prior[-3]:.2f}, free {it.prior[-2]:.2f}, elsewhere {it.prior[-1]:.2f}"
        paper = (f"heads for {t.goal}" if t.goal is not None else "stays at its start (its goal unknown)")
        source = ("its goal " + t.goal if t.goal else "no goal") + (f", candidates {', '.join(t.goals)}" if t.goals
                                                                    else "") + (", stationary" if t.stationary else "")
        out.append(f"  {t.name} ({source}): prior {goals + '; ' if goals else ''}{rest}; the paper's filter: {paper}")
    return out


def _verbs() -> dict:
    """The declared verbs, by name (importlib.metadata.EntryPoint; nothing of them loaded)."""
    from importlib.metadata import entry_points
    return {ep.name: ep for ep in entry_points(group=VERBS) if ep.name not in OWN}


def _name(requirement: str) -> str:
    return re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement).group(1)


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def missing(dist, extra: str, seen: frozenset = frozenset()) -> list[str]:
    """The distributions ``extra`` of ``dist`` (an importlib.metadata Distribution) requires that
    are not installed, following the extras it includes of its own distribution."""
    from importlib import metadata

    out: list[str] = []
    own = _canonical(dist.metadata["Name"])
    for req in dist.requires or []:
        spec, _, marker = req.partition(";")
        if not re.search(r"""extra\s*==\s*['"]%s['"]""" % re.escape(extra), marker):
            continue
        name = _name(spec)
        if _canonical(name) == own:  # passive-monitor[gcs] inside [sim]
            inner = re.search(r"\[([^\]]*)\]", spec)
            for e in (x.strip() for x in (inner.group(1).split(",") if inner else [])):
                if e and e not in seen:
                    out += [m for m in missing(dist, e, seen | {extra}) if m not in out]
            continue
        try:
            metadata.distribution(name)
        except metadata.PackageNotFoundError:
            out.append(name)
    return out


def refusal(prog: str, extras, dist=None) -> str | None:
    """One line saying which extra to install when ``extras`` of ``dist`` (default: this
    distribution) are not all installed, else None."""
    from importlib import metadata

    if dist is None:
        try:
            dist = metadata.distribution("passive-monitor")
        except metadata.PackageNotFoundError:  # run from a source tree: nothing to check against
            return None
    for extra in extras:
        lacking = missing(dist, extra)
        if lacking:
            return (f"{prog}: needs the '{extra}' extra ({', '.join(lacking)} not installed): "
                    f"pip install 'passive-monitor[{extra}]'")
    return None


def _run_verb(name: str, ep, argv: list[str]) -> int:
    if (why := refusal(f"pmon {name}", ep.extras, ep.dist)):
        print(why, file=sys.stderr)
        return 2
    return ep.load()(argv)


def parser(verbs: dict) -> OneLineParser:
    """The top-level parser: ``run`` and ``check-config`` in full, each of ``verbs`` as a name and
    its one line (it parses its own arguments)."""
    from onboard.app import run as run_mod

    ap = OneLineParser(prog="pmon", description="Passive Monitor")  # subparsers are OneLineParsers too
    ap.add_argument("--version", action=Version)
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    r = sub.add_parser("run", help="the onboard app: MAVLink to the autopilot, DF datagrams in",
                       description="The onboard app: MAVLink to the autopilot, DF datagrams in.")
    run_mod.add_arguments(r)
    r.set_defaults(func=run_mod.run)
    c = sub.add_parser("check-config", help="validate a scenario file", description="Validate a scenario file.")
    c.add_argument("scenario", nargs="?", default="paper", help="YAML file or built-in name (default: paper)")
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a scenario value before the checks (VALUE read as YAML; repeatable), as pmon eval's")
    c.set_defaults(func=_check)
    from onboard.app import replay as replay_mod
    rp = sub.add_parser("replay", help="re-run a flight's run log through the core, to the same decisions",
                        description="Re-run a run log through the core: bit for bit, or with --set changes.")
    replay_mod.add_arguments(rp)
    rp.set_defaults(func=replay_mod.run)
    for name, ep in sorted(verbs.items()):
        doc = (ep.load().__doc__ or "").strip().split("\n")[0]
        sub.add_parser(name, help=doc, add_help=False)
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    verbs: dict = {}
    if argv[:1] and argv[0] not in (*OWN, "--version"):
        verbs = _verbs()
        if argv[0] in verbs:
            return _run_verb(argv[0], verbs[argv[0]], argv[1:])
    args = parser(verbs).parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
