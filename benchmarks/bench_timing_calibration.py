"""Are the rate level's confident statements about rotor timing calibrated?

    python benchmarks/bench_timing_calibration.py [--seeds N] [--first S] [--cases none,motor_lag:2,...]
                                                  [--noise white,firmware] [--json FILE] [--table FILE]
                                                  [--sums DIR] [--check] [--found]

Per case (a hidden ``motor_lag`` or ``thrust_delay`` of so many ms, or ``none``), sensor noise
(``white``: the simulator's default; ``firmware``: through the Crazyflie's gyro low-pass,
:data:`quadcore.plan.bench.FIRMWARE_LOWPASS_HZ`) and seed: three 8 s hover flights simulated at
500 Hz (simulator seeds ``10 seed + k``), decoded, and the rate level run on them as the diagnosis
runs it (nominal model, both timing candidates, the diagnosis's folds): the comparison of the pair,
:func:`quadcore.identify.rates.timing_comparison` (``t > 0``: the delay fits better), and each
candidate's reported value and standard error, :func:`quadcore.identify.rates.timing_fit`. The
full diagnosis gives the same numbers (``--check`` runs it too and prints the largest difference);
it takes about twice as long.

Printed per case: the comparison's decisions at ``alpha`` (:class:`DiagnosisSettings`), right,
wrong, undecided (the noise model or the closed loop decides it) or not significant, and the
false-decision rate (``none``: any decision; a truth: a decision for the rival); the mean and
spread of ``t`` (for the truth); for the true candidate (both, at 0, for ``none``) the bias of its
value, the mean and spread of ``z = (θ̂ − θ) / σ̂`` and the coverage of the 1σ and 2σ error bars
(68 % and 95 % if calibrated), and how often it is significant (``|θ̂| / σ̂ ≥ min_sigma``, the
diagnosis's significance). ``--json`` appends each trial as a JSON line (a run resumed with
``--first`` adds to it); ``--table FILE`` prints the summary of such a file and runs nothing; ``--sums DIR`` keeps each
trial's rate sums (pickles, about 3 MB a trial) and reads them back on the next run: a change to the
comparison or the fit is then measured on the same flights without flying them (not a change to
the sums). ``--found`` runs the full diagnosis too and adds, per case, how often it finds each
candidate and how often the row's held-out test passes at its level per candidate (on ``none``: the
false-found rate). docs/benchmarks.md has the measured tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pickle
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_plan import append_line, read_lines

from quadcore import effects
from quadcore.identify import evidence, flightdata, rates
from quadcore.identify.diagnosis.problem import fold_splits
from quadcore.identify.settings import DiagnosisSettings
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.plan.bench import FIRMWARE_LOWPASS_HZ
from quadcore.sim import simulation
from quadcore.sim.simulation import SensorNoise, SimConfig

TIMING = ("thrust_delay", "motor_lag")  # the pair; t > 0: the first fits better
CASES = ("none", "motor_lag:2", "thrust_delay:2", "motor_lag:5", "thrust_delay:5")
NOISE = {"white": 0.0, "firmware": FIRMWARE_LOWPASS_HZ}
HOVER_S = 8.0


@dataclasses.dataclass(frozen=True)
class Trial:
    case: str
    noise: str
    seed: int
    t: float  # the comparison's t (whitened; > 0: thrust_delay fits better)
    p_value: float
    blocks: int
    unwhitened_t: float | None
    instrumented_t: float | None
    undecided_by: str  # "" or what decides the pair in the comparison's place
    fits: dict[str, tuple[float, float]]  # per candidate: the reported value and standard error, s
    seconds: float
    found: dict[str, bool] | None = None  # per candidate: found by the full diagnosis (--found; None: not run)
    held_out: dict[str, tuple[float, float]] | None = None  # per candidate: its row's held-out t and p (--found)

    @property
    def truth(self) -> tuple[str, float]:
        """The hidden candidate and its value (s); ("", 0) for none."""
        if self.case == "none":
            return "", 0.0
        name, ms = self.case.split(":")
        return name, float(ms) / 1e3

    def decision(self, alpha: float) -> str:
        """What the diagnosis makes of the pair: the candidate preferred, ``undecided`` or ``not
        significant``."""
        if self.undecided_by:
            return "undecided"
        if not self.p_value < alpha:
            return "not significant"
        return TIMING[0] if self.t > 0 else TIMING[1]


def run(case: str, noise: str, seed: int, check: bool = False, keep: Path | None = None,
        found: bool = False) -> Trial:
    """One trial: the hovers flown with ``case`` hidden, the rate level on them (module); ``keep``:
    a folder to keep the flights' rate sums in, read back when there (no flight then, unless the
    full diagnosis is run: ``check``, its numbers against these; ``found``, which candidates it finds)."""
    veh = vehicle.load()
    settings = DiagnosisSettings()
    timing = [effects.get(n) for n in TIMING]
    t0 = time.perf_counter()
    kept = None if keep is None else keep / f"{case.replace(':', '_')}_{noise}_{seed}.pickle"
    tables = fly(case, noise, seed, veh) if check or found or kept is None or not kept.exists() else None
    if tables is None and kept is not None:
        sums = pickle.loads(kept.read_bytes())
    else:
        assert tables is not None
        skip = evidence.memory_blocks(timing)
        sums = {f: rates.rate_sums(rates.rate_flight(flightdata.flight_data(f, tab, veh), veh, None, skip), timing)
                for f, tab in tables.items()}
        if kept is not None and not kept.exists():
            kept.parent.mkdir(parents=True, exist_ok=True)
            kept.with_suffix(".part").write_bytes(pickle.dumps(sums))
            kept.with_suffix(".part").replace(kept)
    splits, train_all, _ = fold_splits(sorted(sums), None, settings.n_folds)
    pair = rates.timing_comparison(sums, splits, timing[0], timing[1], settings.alpha)
    fits = {}
    for c in timing:
        rf, spread = rates.timing_fit(c, sums, splits, train_all, settings.n_folds)
        fits[c.name] = (rf.value, max(rf.std, spread))
    trial = Trial(case, noise, seed, pair.test.t, pair.test.p_value, pair.test.blocks,
                  None if pair.unwhitened is None else pair.unwhitened.t,
                  None if pair.instrumented is None else pair.instrumented.t, pair.undecided_by, fits,
                  time.perf_counter() - t0)
    if tables is not None and (check or found):
        rows, diagnosed_pair = diagnosed(tables, veh)
        if check:
            print(f"  the full diagnosis against the rate level alone: {difference(trial, rows, diagnosed_pair)}")
        trial = dataclasses.replace(trial, found={n: bool(rows[n].found) for n in TIMING},
                                    held_out={n: (float(rows[n].held_out_t), float(rows[n].held_out_p_value))
                                              for n in TIMING}, seconds=time.perf_counter() - t0)
    return trial


def fly(case: str, noise: str, seed: int, veh) -> dict:
    """The three hovers of a trial, flown with ``case`` hidden and decoded: their tables by flight."""
    hidden: dict[str, dict[str, float]] = {}
    if case != "none":
        name, ms = case.split(":")
        hidden = {name: {effects.get(name).parameters[0].name: float(ms) / 1e3}}
    with tempfile.TemporaryDirectory() as tmp:
        configs = [SimConfig(kind="hover", duration_s=HOVER_S, seed=10 * seed + k, log_rate_hz=500.0,
                             noise=SensorNoise(lowpass_hz=NOISE[noise])) for k in range(3)]
        simulation.simulate_set(tmp, configs, hidden, veh)
        return {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(Path(tmp))}


def diagnosed(tables: dict, veh) -> tuple[dict, rates.PairComparison]:
    """The full diagnosis of a trial's flights with the two timing candidates (nominal model): its
    rows by candidate, and the pair's comparison as it made it."""
    from quadcore.identify import diagnosis
    from quadcore.identify.rates import judgement
    from quadcore.spec.model import spec_from

    seen: list[rates.PairComparison] = []
    compare = judgement.timing_comparison

    def spy(*args, **kwargs):
        seen.append(compare(*args, **kwargs))
        return seen[-1]

    judgement.timing_comparison = spy
    try:
        diag = diagnosis.diagnose(tables, spec_from(veh, []), candidates=list(TIMING))
    finally:
        judgement.timing_comparison = compare
    (pair,) = seen
    return {c.effect: c for c in diag.candidates}, pair


def difference(trial: Trial, rows: dict, pair: rates.PairComparison) -> str:
    """The largest relative difference between ``trial``'s numbers and the full diagnosis's on the
    same flights (its reported values and standard errors, the comparison's t)."""
    ours, theirs = [], []
    for name, (v, s) in trial.fits.items():
        (p,) = effects.get(name).parameters
        ours += [v, s]
        theirs += [rows[name].parameters[p.name], rows[name].parameter_std[p.name]]
    sign = 1.0 if pair.a == TIMING[0] else -1.0
    ours.append(trial.t)
    theirs.append(sign * pair.test.t)
    diff = max(abs(a - b) / max(abs(b), 1e-300) for a, b in zip(ours, theirs))
    return f"{diff:.1e} relative (values, standard errors, t)"


def _found(ts: list[Trial], names: list[str], rival: str) -> str:
    """How often the full diagnosis found each of ``names`` (and ``rival``) in the trials it ran on,
    and how often their rows' held-out test passed at the library's ``alpha`` per candidate (the
    diagnosis's other condition, besides the fit's significance)."""
    ran = [tr.found for tr in ts if tr.found is not None]
    if not ran:
        return "not run"
    label = len(names) > 1
    out = [(f"{n}: " if label else "") + _rate(sum(f[n] for f in ran), len(ran)) for n in names]
    confirmed = [tr.held_out for tr in ts if tr.held_out is not None]
    if confirmed:  # the row's held-out test at the diagnosis's level per candidate (two candidates here)
        alpha = evidence.alpha_each(len(TIMING), DiagnosisSettings().alpha)
        out += [f"held out p < {alpha:g}, {n}: " + _rate(sum(h[n][1] < alpha for h in confirmed), len(confirmed))
                for n in names]
    return "; ".join(out + ([f"the rival {_rate(sum(f[rival] for f in ran), len(ran))}"] if rival else []))


def _rate(k: int, n: int) -> str:
    return f"{k}/{n}" + (f" ({100 * k / n:.0f} %)" if n else "")


def summarise(trials: list[Trial], alpha: float, min_sigma: float) -> None:
    """Per case and noise: the decisions, t, and the true candidate's z and coverage (module)."""
    by: dict[tuple[str, str], list[Trial]] = {}
    for tr in trials:
        by.setdefault((tr.case, tr.noise), []).append(tr)
    print(f"\nalpha {alpha}, min_sigma {min_sigma}; t > 0 favours {TIMING[0]}; z = (fitted - truth) / reported σ")
    print("| case | noise | seeds | decisions (truth / rival / undecided / not significant) | false decisions | "
          "t toward the truth: mean ± se (sd) | value − truth, ms: mean ± se | z: mean (sd) | within 1σ | within 2σ "
          "| significant | found by the diagnosis (--found) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (case, noise), ts in sorted(by.items(), key=lambda kv: (CASES.index(kv[0][0]) if kv[0][0] in CASES else 99,
                                                                 kv[0][1])):
        n = len(ts)
        truth, value = ts[0].truth
        decisions = [tr.decision(alpha) for tr in ts]
        counts = {d: decisions.count(d) for d in (*TIMING, "undecided", "not significant")}
        if truth:
            rival = next(x for x in TIMING if x != truth)
            said = f"{counts[truth]} / {counts[rival]} / {counts['undecided']} / {counts['not significant']}"
            false = counts[rival]
            toward = [tr.t if truth == TIMING[0] else -tr.t for tr in ts]
            names = [truth]
        else:
            said = f"{counts[TIMING[0]]} {TIMING[0]}, {counts[TIMING[1]]} {TIMING[1]} / {counts['undecided']} / " \
                   f"{counts['not significant']}"
            false = counts[TIMING[0]] + counts[TIMING[1]]
            toward = [tr.t for tr in ts]
            names = list(TIMING)
        t_sd = statistics.stdev(toward) if n > 1 else float("nan")
        cells = []
        for name in names:
            err = [tr.fits[name][0] - value for tr in ts]
            z = [e / tr.fits[name][1] if tr.fits[name][1] > 0 else math.copysign(math.inf, e) for e, tr in zip(err, ts)]
            sig = sum(abs(tr.fits[name][0]) / tr.fits[name][1] >= min_sigma if tr.fits[name][1] > 0
                      else tr.fits[name][0] != 0 for tr in ts)
            finite = [x for x in z if math.isfinite(x)]
            bias = 1e3 * statistics.mean(err)
            bias_se = 1e3 * statistics.stdev(err) / math.sqrt(n) if n > 1 else float("nan")
            z_sd = statistics.stdev(finite) if len(finite) > 1 else float("nan")
            label = "" if truth else f"{name}: "
            cells.append((f"{label}{bias:+.2f} ± {bias_se:.2f}",
                          f"{label}{statistics.mean(finite) if finite else float('nan'):+.2f} ({z_sd:.2f})",
                          label + _rate(sum(abs(x) <= 1 for x in z), n), label + _rate(sum(abs(x) <= 2 for x in z), n),
                          label + _rate(sig, n)))
        found = _found(ts, names if truth else list(TIMING), "" if not truth else rival)
        cols = ["; ".join(c[i] for c in cells) for i in range(5)] + [found]
        print(f"| {case} | {noise} | {n} | {said} | {_rate(false, n)} | {statistics.mean(toward):+.2f} ± "
              f"{t_sd / math.sqrt(n):.2f} ({t_sd:.2f}) | " + " | ".join(cols) + " |")


def found_note(tr: Trial) -> str:
    """"; found: ..." for a trial the full diagnosis ran on ("" otherwise)."""
    return "" if tr.found is None else f"; found: {', '.join(n for n, f in tr.found.items() if f) or 'none'}"


def read_trials(path: str) -> list[Trial]:
    """The trials of a ``--json`` file (lines a killed run left unfinished are left out: bench_plan's
    :func:`read_lines`)."""
    def pairs(x: dict | None) -> dict | None:
        return None if x is None else {n: tuple(v) for n, v in x.items()}

    return [Trial(**{**d, "fits": pairs(d["fits"]), "held_out": pairs(d.get("held_out"))}) for d in read_lines(path)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first", type=int, default=0, help="first seed (to resume a run)")
    ap.add_argument("--cases", default=",".join(CASES), help="none, or EFFECT:MS of motor_lag, thrust_delay")
    ap.add_argument("--noise", default=",".join(NOISE), help="white, firmware")
    ap.add_argument("--json", help="append each trial to this file as a JSON line")
    ap.add_argument("--table", help="print the summary of the trials in this --json file, run nothing")
    ap.add_argument("--sums", help="keep each trial's rate sums in this folder and read them back when there "
                    "(a change to the comparison is then measured on the same flights without flying them again)")
    ap.add_argument("--check", action="store_true", help="also run the full diagnosis and print the difference")
    ap.add_argument("--found", action="store_true",
                    help="also run the full diagnosis and count the candidates it finds (the false-found rate)")
    args = ap.parse_args()
    settings = DiagnosisSettings()
    if args.table:
        summarise(read_trials(args.table), settings.alpha, settings.min_sigma)
        return
    trials = []
    keep = Path(args.sums) if args.sums else None
    for seed in range(args.first, args.first + args.seeds):  # every case's seed before the next seed
        for noise in args.noise.split(","):
            for case in args.cases.split(","):
                tr = run(case, noise, seed, args.check, keep, args.found)
                trials.append(tr)
                fits = ", ".join(f"{n} {1e3 * v:.2f} ± {1e3 * s:.2f} ms" for n, (v, s) in tr.fits.items())
                extra = "".join(f", {k} {v:+.2f}" for k, v in (("unwhitened", tr.unwhitened_t),
                                                               ("instrumented", tr.instrumented_t)) if v is not None)
                print(f"{case} {noise} seed {seed}: t {tr.t:+.2f} (p {tr.p_value:.3g}{extra}) -> "
                      f"{tr.decision(settings.alpha)}{' by ' + tr.undecided_by if tr.undecided_by else ''}; {fits}"
                      f"{found_note(tr)} ({tr.seconds:.0f} s)", flush=True)
                if args.json:
                    append_line(args.json, json.dumps(dataclasses.asdict(tr)))
    summarise(trials, settings.alpha, settings.min_sigma)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
