"""Does one planned flight decide what the logged flights leave open, and better than a flight of
the same length from the lab's trajectory files?

    python benchmarks/bench_plan.py [--seeds N] [--first S] [--scenarios drag,mass,lag,lag_small]

Per scenario of :mod:`quadcore.plan.bench` (rotor vs parasitic drag on flights at one speed;
thrust scale vs added mass in hover; motor lag vs thrust delay in hover, at 10 ms and at 2 ms)
and seed: three flights simulated with the hidden truth (alternating between the two sides with the seed), diagnosed;
``quadcore plan``'s planner asked to separate the two (``--between``, 10 s manoeuvre, default
limits); the plan flown in the simulator with the truth and added to the old flights; and, for
comparison, each of the lab's files (figure8, circle0, yaw0) flown for the same time instead.
"decided" = the diagnosis ranks the truth first and no longer ties it with the other. Prints a
line per trial and the counts. CI runs two seeds per scenario without the files
(``tests/test_plan.py``); this runs all of them.
"""

from __future__ import annotations

import argparse
import time

from quadcore.plan import bench


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="first seed (to resume a run)")
    ap.add_argument("--scenarios", default=",".join(bench.SCENARIOS))
    args = ap.parse_args()
    totals: dict[str, dict[str, int]] = {}
    for name in args.scenarios.split(","):
        counts = totals.setdefault(name, {"planned": 0, **{f: 0 for f in bench.FILES}, "best file": 0, "before": 0})
        for seed in range(args.first, args.first + args.seeds):
            t0 = time.perf_counter()
            trial = bench.run(name, seed)
            counts["planned"] += trial.planned.decided
            counts["before"] += trial.before.decided
            for f, o in trial.files.items():
                counts[f] += o.decided
            counts["best file"] += any(o.decided for o in trial.files.values())
            files = "; ".join(f"{f}: {o.describe()}" for f, o in trial.files.items())
            print(f"{name} seed {seed} truth {trial.truth}: before {trial.before.describe()} | planned "
                  f"({trial.manoeuvre}; predicted {trial.predicted_sigma:.1f} σ): {trial.planned.describe()} | "
                  f"{files} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"\ndecided (truth first, not tied with the other) in {args.seeds} seeds:")
    print(f"{'scenario':10s} {'before':>7s} {'planned':>8s} " + " ".join(f"{f:>8s}" for f in bench.FILES)
          + f" {'any file':>9s}")
    for name, c in totals.items():
        print(f"{name:10s} {c['before']:7d} {c['planned']:8d} " + " ".join(f"{c[f]:8d}" for f in bench.FILES)
              + f" {c['best file']:9d}")


if __name__ == "__main__":
    main()
