"""Does one planned flight decide what the logged flights leave open, and better than a flight of
the same length from the lab's trajectory files?

    python benchmarks/bench_plan.py [--seeds N] [--first S] [--scenarios drag,mass,lag,lag_small]

Per scenario of :mod:`quadcore.plan.bench` (rotor vs parasitic drag on flights at one speed;
thrust scale vs added mass in hover; motor lag vs thrust delay in hover, at 10 ms and at 2 ms)
and seed: three flights simulated with the hidden truth (alternating between the two sides with the seed), diagnosed;
``quadcore plan``'s planner asked to separate the two (``--between``, 10 s manoeuvre, default
limits); the plan flown in the simulator with the truth and added to the old flights; and, for
comparison, each of the lab's files (figure8, circle0, yaw0) flown for the same time instead.
"decided" = the diagnosis ranks the truth first and no longer ties it with the other; "σ" the
separation in favour of the truth in the statistic the diagnosis decides the pair by (the
held-out comparison's t; for a lag against a delay the angular-rate level's,
:func:`quadcore.plan.separation.measured`), so "does worse" is a number, not only a count; the
design's predicted σ beside the one achieved with the planned flight. ``--files`` chooses the
comparison flights (``hover``: a hover of the same length). Prints a line per trial (and with
``--json`` appends it to that file as a JSON line) and the counts with the median σ. CI runs
two seeds per scenario without the files (``tests/test_plan.py``); this runs all of them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

from quadcore.plan import bench


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="first seed (to resume a run)")
    ap.add_argument("--scenarios", default=",".join(bench.SCENARIOS))
    ap.add_argument("--files", default=",".join(bench.FILES),
                    help="comparison flights of the same length: " + ", ".join((*bench.FILES, "hover")) + " ('' none)")
    ap.add_argument("--json", help="append each trial to this file as a JSON line")
    args = ap.parse_args()
    files = tuple(f for f in args.files.split(",") if f)
    totals: dict[str, dict[str, list]] = {}
    for name in args.scenarios.split(","):
        res = totals.setdefault(name, {})
        for seed in range(args.first, args.first + args.seeds):
            t0 = time.perf_counter()
            trial = bench.run(name, seed, files)
            for label, o in (("before", trial.before), ("planned", trial.planned), *trial.files.items()):
                res.setdefault(label, []).append(o)
            res.setdefault("any file", []).append(any(o.decided for o in trial.files.values()))
            described = "; ".join(f"{f}: {o.describe()}" for f, o in trial.files.items())
            print(f"{name} seed {seed} truth {trial.truth}: before {trial.before.describe()} (predicted "
                  f"{trial.predicted_before:.1f} σ) | planned ({trial.manoeuvre}; predicted "
                  f"{trial.predicted_sigma:.1f} σ): {trial.planned.describe()} | {described} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
            if trial.added:
                flights = "; ".join(f"{x.flight} {x.seconds:.1f} s " + "/".join(f"{t:.1f}" for t in x.own.values())
                                    + f" ({x.per_second():.2f}/s)" for x in trial.added)
                print(f"  predicted at the rate level, the flight's own blocks (t per truth; min t² per s): {flights}",
                      flush=True)
                for x in trial.added:
                    res.setdefault(f"per second {x.flight}", []).append(x.per_second())
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps(dataclasses.asdict(trial)) + "\n")
    print("\ndecided (truth first, not tied with the other) of the seeds, and the median separation σ for the truth:")
    labels = ("before", "planned", *files)
    print(f"{'scenario':12s} " + " ".join(f"{f:>15s}" for f in labels) + f" {'any file':>9s}")
    for name, res in totals.items():
        cells = [f"{sum(o.decided for o in res[f]):2d} ({statistics.median(o.sigma for o in res[f]):+6.1f} σ)"
                 for f in labels]
        print(f"{name:12s} " + " ".join(f"{c:>15s}" for c in cells) + f" {sum(res['any file']):9d}")
        rate = {k.removeprefix("per second "): v for k, v in res.items() if k.startswith("per second ")}
        if rate:
            print(f"{'':12s} predicted rate-level t² per second of the added flight alone (median, smaller over the "
                  "truths): " + ", ".join(f"{k} {statistics.median(v):.2f}" for k, v in rate.items()))


if __name__ == "__main__":
    main()
