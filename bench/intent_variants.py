"""The intent filter's constants and settings varied on a few trials (exploration, not the flight path).

    python -m bench.intent_variants KIND TRIALS [NAME=VALUE,...] [--set KEY=VALUE ...]

Runs ``pmon eval``'s trials (seed 2024, method flight@stock, truth ``KIND`` of sim/truth/kinds.py,
``KIND+told`` for a told filter) in this process, one after the other, with module constants of
onboard/core/tracking changed first (``MIN_MODE_SHARE=0.02`` for onboard/core/tracking/intent.py,
``intent_tick.PLAN_MODES=1`` for another module of that folder), and prints one line: the RMSE, ANEES, the
share of target-ticks more than 100 m off, the targets lost at the end, the true mode's
probability at 40 s and the per-trial RMSEs. In-process: BLAS keeps its threads and the kernels
are not pinned, so the figures are this machine's and may differ in the last digits from
``pmon eval``'s; compare variants within this script only (docs/LOG.md, "Intent").
"""
from __future__ import annotations

import argparse
import importlib

import numpy as np

from bench import add_set_option, set_overrides


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("trials", type=int)
    ap.add_argument("constants", nargs="?", default="", help="NAME=VALUE,... of onboard/core/tracking modules")
    add_set_option(ap, "tracking.intent_switch_prob=0.01")
    args = ap.parse_args(argv)
    from onboard.config import load_scenario
    from sim.evaluation import trials as ev

    for kv in filter(None, args.constants.split(",")):
        key, _, value = kv.partition("=")
        mod, _, name = key.rpartition(".")
        module = importlib.import_module("onboard.core.tracking." + (mod or "intent"))
        if not hasattr(module, name):
            ap.error(f"no constant {name} in onboard.core.tracking.{mod or 'intent'}")
        setattr(module, name, type(getattr(module, name))(float(value)))
    sc = load_scenario("paper", set_overrides(ap, args))
    told = args.kind.endswith("+told")
    kind = args.kind.removesuffix("+told")
    cfg = ev.make_config(sc, args.trials, 2024, ["flight@stock"], truth=kind, told=told)
    s = ev.summarise(cfg, [ev.run_trial(cfg, i) for i in range(args.trials)]).methods["flight@stock"]
    t = s.truth
    print(f"{args.kind} {args.constants} {' '.join(args.set)}: rmse {s.rmse_mean_m:.1f} anees {s.nees_mean:.2f} "
          f"far {t['far_fraction']:.3f} lost {t['lost_at_end']}/{t['targets']} "
          f"p90@40 {t.get('true_mode_p90_at_40s')} per_trial {np.round(s.per_trial_rmse, 1).tolist()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
