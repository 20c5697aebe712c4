"""Does one planned flight decide what the logged flights leave open, and better than a flight of
the same length from the lab's trajectory files?

    python benchmarks/bench_plan.py [--seeds N] [--first S] [--scenarios drag,mass,lag,lag_small]
                                    [--max-speed MPS] [--max-acc MPS2] [--max-tilt DEG]

Per scenario of :mod:`quadcore.plan.bench` (rotor vs parasitic drag on flights at one speed;
thrust scale vs added mass in hover; motor lag vs thrust delay in hover, at 10 ms and at 2 ms)
and seed: three flights simulated with the hidden truth (alternating between the two sides with the seed), diagnosed;
``quadcore plan``'s planner asked to separate the two (``--between``, 10 s manoeuvre, default
limits unless ``--max-speed``/``--max-acc``/``--max-tilt`` give others, as ``quadcore plan``'s
options do: to allow the plan what a file flies; each trial's JSON line records them); the plan
flown in the simulator with the truth and added to the old flights; and, for comparison, each of
the lab's files (figure8, circle0, yaw0) flown for the same time instead.
"decided" = the diagnosis ranks the truth first and no longer ties it with the other; "σ" the
separation in favour of the truth in the statistic the diagnosis decides the pair by (the held-out
comparison's t; for a lag against a delay the angular-rate level's,
:func:`quadcore.plan.separation.measured`: 0 and marked "(noise model)" or "(closed loop)" where the
gyro noise model or the closed loop decides it and the diagnosis prefers neither), so "does worse"
is a number, not only a count; the design's predicted σ beside the one achieved with the planned
flight. ``--files`` chooses the comparison flights (``hover``: a hover of the same length). Prints a
line per trial (and with ``--json`` appends it to that file as a JSON line), a table per scenario of
each seed's σ per flight (the docs' tables), and the counts with the median σ; ``--table FILE``
prints the tables and counts of the trials a ``--json`` run wrote (several runs, resumed ones, in
one table) without running anything. CI runs two seeds per scenario without the files
(``tests/test_plan.py``); this runs all of them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time

from quadcore.plan import bench
from quadcore.plan.limits import Limits, LimitsError


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="first seed (to resume a run)")
    ap.add_argument("--scenarios", default=",".join(bench.SCENARIOS))
    ap.add_argument("--files", default=",".join(bench.FILES),
                    help="comparison flights of the same length: " + ", ".join((*bench.FILES, "hover")) + " ('' none)")
    ap.add_argument("--max-speed", type=float, help=f"the plan's speed limit, m/s (default {Limits().max_speed_mps})")
    ap.add_argument("--max-acc", type=float, help="the plan's acceleration limit, m/s² (default: what the tilt allows)")
    ap.add_argument("--max-tilt", type=float, help=f"the plan's tilt limit, degrees (default {Limits().max_tilt_deg})")
    ap.add_argument("--json", help="append each trial to this file as a JSON line")
    ap.add_argument("--table", help="print the tables of the trials in this --json file, run nothing")
    args = ap.parse_args()
    if args.table:
        summarise([trial_from(d) for d in read_lines(args.table)])
        return
    files = tuple(f for f in args.files.split(",") if f)
    try:
        limits = Limits(**{k: v for k, v in (("max_speed_mps", args.max_speed), ("max_acc_mps2", args.max_acc),
                                             ("max_tilt_deg", args.max_tilt)) if v is not None})
    except LimitsError as exc:
        ap.error(str(exc))
    trials = []
    for name in args.scenarios.split(","):
        for seed in range(args.first, args.first + args.seeds):
            t0 = time.perf_counter()
            trial = bench.run(name, seed, files, limits=limits)
            trials.append(trial)
            described = "; ".join(f"{f}: {o.describe()}" for f, o in trial.files.items())
            peaks = trial.checked
            print(f"{name} seed {seed} truth {trial.truth}: before {trial.before.describe()} (predicted "
                  f"{trial.predicted_before:.1f} σ) | planned ({trial.manoeuvre}; peaks {peaks['max_speed_mps']:.2f} "
                  f"m/s, {peaks['max_acc_mps2']:.1f} m/s², {peaks['max_tilt_deg']:.1f}°; predicted "
                  f"{trial.predicted_sigma:.1f} σ): {trial.planned.describe()} | {described} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
            if trial.added:
                flights = "; ".join(f"{x.flight} {x.seconds:.1f} s " + "/".join(f"{t:.1f}" for t in x.own.values())
                                    + f" ({x.per_second():.2f}/s)" for x in trial.added)
                print(f"  predicted at the rate level, the flight's own blocks (t per truth; min t² per s): {flights}",
                      flush=True)
            if args.json:
                append_line(args.json, json.dumps(dataclasses.asdict(trial)))
    summarise(trials)


def read_lines(path: str) -> list[dict]:
    """The JSON lines of a ``--json`` file; a line that is not complete JSON (a run killed
    mid-write, then perhaps resumed after it: :func:`append_line`) is left out with a message."""
    rows = []
    with open(path) as fh:
        for k, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                print(f"bench_plan: {path} line {k} is not complete JSON (a run killed mid-write?): left out",
                      file=sys.stderr)
    return rows


def append_line(path: str, line: str) -> None:
    """Append ``line`` to ``path`` on a line of its own (after a last line a killed run left unfinished)."""
    with open(path, "ab+") as fh:  # appends go to the end whatever the position read from
        ended = fh.seek(0, os.SEEK_END) == 0 or (fh.seek(-1, os.SEEK_END) >= 0 and fh.read(1) == b"\n")
        fh.write((("" if ended else "\n") + line + "\n").encode())


def trial_from(d: dict) -> bench.Trial:
    """A :class:`bench.Trial` from its ``--json`` line."""
    return bench.Trial(**{**d, "before": bench.Outcome(**d["before"]), "planned": bench.Outcome(**d["planned"]),
                          "files": {f: bench.Outcome(**o) for f, o in d["files"].items()},
                          "added": tuple(bench.Added(**x) for x in d["added"])})


def cell(o: bench.Outcome, rival: str) -> str:
    """One flight's σ for the truth, and what the diagnosis said when it did not decide; 'first
    against σ': decided, but the comparison favours the rival (the truth ranked first across
    tiers: the rival's fit not significant)."""
    noise = ""  # the diagnosis prefers neither at the rate level: σ 0, and the t it sets aside
    if o.undecided:
        noise = f" ({o.why_undecided}" + (f", t {o.t:+.1f})" if o.t == o.t else ")")
    if o.decided:
        return f"{o.sigma:+.1f}" + (" first against σ" if o.sigma < 0 else "") + noise
    why = "tied" if o.tied else ("wrong" if o.top == rival else f"{o.top} first")
    return f"{o.sigma:+.1f} {why}{noise}"


def label(t: bench.Trial) -> str:
    """The scenario's name, and the plan's limits where they are not the default ones."""
    lim, default = t.limits, Limits().to_dict()
    if all(lim.get(k, v) == v for k, v in default.items()):
        return t.scenario
    return (f"{t.scenario} (plan limits: {lim['max_speed_mps']:g} m/s, {lim['max_acc_mps2']:g} m/s², "
            f"{lim['max_tilt_deg']:g}°)")


def summarise(trials: list[bench.Trial]) -> None:
    """Per scenario (and the plan's limits, where not the default) a table of each seed's σ per
    flight (markdown), then the counts and medians."""
    by_name: dict[str, list[bench.Trial]] = {}
    for t in trials:
        by_name.setdefault(label(t), []).append(t)
    for name, ts in by_name.items():
        files = list(dict.fromkeys(f for t in ts for f in t.files))
        pair = bench.SCENARIOS[ts[0].scenario].pair
        print(f"\n{name}: σ for the truth per seed (decided unless marked: 'tied', 'wrong' = the rival first "
              "untied, or the effect ranked first; 'first against σ': decided, the comparison favouring the rival; "
              "(closed loop, t) / (noise model, t): the rate level prefers neither for that reason, σ 0, t set aside)")
        print("| seed (truth) | before | plan (predicted) | " + " | ".join(files) + " |")
        print("|---" * (3 + len(files)) + "|")
        for t in sorted(ts, key=lambda t: (t.truth != pair[0], t.seed)):
            rival = pair[1] if t.truth == pair[0] else pair[0]
            cells = [cell(t.before, rival), f"{cell(t.planned, rival)} ({t.predicted_sigma:.0f})",
                     *(cell(t.files[f], rival) if f in t.files else "" for f in files)]
            print(f"| {t.seed} ({t.truth}) | " + " | ".join(cells) + " |")
        print("| decided, of them against σ (median σ) | " + " | ".join(
            f"{sum(o.decided for o in os)}, {sum(o.decided and o.sigma < 0 for o in os)} "
            f"({statistics.median(o.sigma for o in os):+.1f})"
            for os in ([t.before for t in ts], [t.planned for t in ts],
                       *([t.files[f] for t in ts if f in t.files] for f in files))) + " |")
    print("\ndecided (truth first, not tied with the other) of the seeds, and the median separation σ for the truth:")
    for name, ts in by_name.items():
        files = list(dict.fromkeys(f for t in ts for f in t.files))
        cols = {"before": [t.before for t in ts], "planned": [t.planned for t in ts],
                **{f: [t.files[f] for t in ts if f in t.files] for f in files}}
        print(f"{'scenario':16s} " + " ".join(f"{f:>15s}" for f in cols) + f" {'any file':>9s} (of the lab's files)")
        cells = [f"{sum(o.decided for o in os):2d} ({statistics.median(o.sigma for o in os):+6.1f} σ)"
                 for os in cols.values()]
        anyfile = sum(any(o.decided for f, o in t.files.items() if f != "hover") for t in ts)
        print(f"{name:16s} " + " ".join(f"{c:>15s}" for c in cells) + f" {anyfile:9d}")
        rate: dict[str, list[float]] = {}
        for t in ts:
            for x in t.added:
                rate.setdefault(x.flight, []).append(x.per_second())
        if rate:
            print(f"{'':16s} predicted rate-level t² per second of the added flight alone (median, smaller over the "
                  "truths): " + ", ".join(f"{k} {statistics.median(v):.2f}" for k, v in rate.items()))


if __name__ == "__main__":
    main()
