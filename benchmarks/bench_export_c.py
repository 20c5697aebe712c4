"""The exported C model on the real flights: time per call on this machine beside Python's
per-sample figure, the footprint beside the STM32F405's budget, and a labelled cycle estimate
for the Cortex-M4.

    python benchmarks/bench_export_c.py [LOGS_FOLDER]

Physics model: rotor drag, CoM offset, thrust scale and motor lag fitted on 18 flights
(jana02 held out). Learned residual on top: the best XGBoost and the best MLP among a few
candidates, "best" by validation loss (as the learning report chooses). Each is exported,
compiled with ``-O2`` and run on every row of jana02 through ctypes (the loop over rows in C;
the time per call includes copying the row into the input struct).

Targets (issue 16): physics + XGBoost under 5 us per call here; flash and RAM within 10 % of
the STM32F405's 1 MB and 192 KB.
"""

import os
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import logs_folder

from quadcore.export import c as export_c
from quadcore.export.c.build import STM32F405_FLASH_BYTES, STM32F405_RAM_BYTES
from quadcore.identify.fit import model_fit
from quadcore.learn import artefacts, features as feat, learners, trainers, trees
from quadcore.logs import flight
from quadcore.physics import dynamics, vehicle
from quadcore.spec.model import spec_from

HOLDOUT = "jana02"
EFFECTS = ["rotor_drag", "com_offset", "thrust_scale", "motor_lag"]
CANDIDATES = {
    "xgboost": [replace(learners.default_spec("xgboost"), max_depth=d) for d in (4, 6)],
    "mlp": [replace(learners.default_spec("mlp"), hidden=h) for h in ((), (64, 64))],
}
SETS = ("physics", "physics_rate")
CLOCK_HZ = 168e6
# Cortex-M4 cost assumptions for the estimate (cycles), low / high: a tree split visited is ~10
# instructions (three byte/halfword loads, compare, select, flag test, branch); high adds a flash
# wait-state miss (5 at 168 MHz) for the node, which the ART cache mostly hides for sequential code
# but not for nodes scattered over ~100 KB. A multiply-add: VLDR x2 + VFMA (pipelined) to a miss
# every four weights. The physics part: its compiled instructions once, to twice (loops over rotors).
SPLIT_CYCLES = (10, 16)
BISECT_CYCLES = (8, 14)
MAC_CYCLES = (3, 6)


def arm_function_bytes(source_dir: Path, name: str) -> int | None:
    """Bytes of one function compiled for the Cortex-M4 (None without arm-none-eabi-gcc)."""
    from quadcore.export.c import build

    cc, nm = shutil.which("arm-none-eabi-gcc"), shutil.which("arm-none-eabi-nm")
    if not cc or not nm:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "include").mkdir()
        (Path(tmp) / "include" / "math.h").write_text(build.ARM_MATH_H)
        obj = Path(tmp) / "m.o"
        build._run([cc, "-std=c99", *build.CORTEX_M4, "-Os", "-fno-math-errno", f"-I{tmp}/include",
                    f"-I{source_dir}", "-c", str(source_dir / "quadcore_model.c"), "-o", str(obj)], Path(tmp))
        out = build.subprocess.run([nm, "-S", "--size-sort", str(obj)], capture_output=True, text=True).stdout
    sizes = {line.split()[-1]: int(line.split()[1], 16) for line in out.splitlines() if len(line.split()) == 4}
    return sizes.get(name)


def cycle_estimate(learned, X, physics_bytes: int | None) -> tuple[float, float, str]:
    """(low, high) cycles per call and how they were counted."""
    if learned.kind == "xgboost":
        forest = trees.CompiledForest(learned.impl)
        z = learned.x_scaler.transform(X)
        node = np.broadcast_to(forest.roots, (len(z), len(forest.roots))).copy()
        rows = np.arange(len(z))[:, None]
        visited = np.zeros(len(z))
        for _ in range(forest.depth):
            internal = forest.left[node] != node
            visited += internal.sum(axis=1)
            xv = z[rows, forest.feature[node]]
            node = np.where(xv < forest.threshold[node], forest.left[node], forest.right[node])
        splits = float(visited.mean())
        cuts = [np.unique(forest.threshold[(forest.left != np.arange(len(forest.left))) & (forest.feature == f)]).size
                for f in range(len(learned.features))]
        bisect = float(sum(np.ceil(np.log2(c + 1)) for c in cuts))
        low = splits * SPLIT_CYCLES[0] + bisect * BISECT_CYCLES[0]
        high = splits * SPLIT_CYCLES[1] + bisect * BISECT_CYCLES[1]
        how = f"{splits:.0f} splits visited per call (mean over the rows), {bisect:.0f} bisection steps"
    else:
        import torch.nn as nn

        macs = sum(m.in_features * m.out_features for m in learned.impl if isinstance(m, nn.Linear))
        low, high = macs * MAC_CYCLES[0], macs * MAC_CYCLES[1]
        how = f"{macs} multiply-adds"
    if physics_bytes:
        instructions = physics_bytes / 3  # Thumb-2: a mix of 2- and 4-byte instructions
        low, high = low + instructions, high + 2 * instructions
        how += f", physics part ~{instructions:.0f} instructions ({physics_bytes} B of Thumb-2)"
    return low, high, how


def main() -> None:
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        print("no C compiler: install gcc")
        sys.exit(0)
    folder = logs_folder()
    veh = vehicle.load()
    decoded = {f.flight_id: f.tables["fixedFrequency"] for f in map(flight.decode_flight, flight.discover_logs(folder))}
    if HOLDOUT not in decoded:
        print(f"{HOLDOUT} not among the logs in {folder}")
        sys.exit(0)
    train = sorted(f for f in decoded if f != HOLDOUT)
    t0 = time.perf_counter()
    physics = model_fit.fit_model(spec_from(veh, EFFECTS), decoded, train)
    print(f"physics model {physics.label} fitted on {len(train)} flights in {time.perf_counter() - t0:.0f} s; "
          f"held out {HOLDOUT}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    res = {f: physics.residual_table(df) for f, df in decoded.items()}
    tables = feat.feature_tables(res, [feat.FEATURE_SETS[s] for s in SETS])
    candidates: dict[str, artefacts.LearnedModel] = {}  # per spec, its best feature set
    for kind, specs in CANDIDATES.items():
        for spec in specs:
            for s in SETS:
                m = trainers.train(spec, feat.FEATURE_SETS[s], tables[s], train, learners.TrainConfig(),
                                   {**physics.to_dict(), "trained_on": train})
                print(f"  {kind:8s} {spec.slug:14s} {s:13s} val loss {m.manifest['val_loss']:.4f}")
                if spec.slug not in candidates or m.manifest["val_loss"] < candidates[spec.slug].manifest["val_loss"]:
                    candidates[spec.slug] = m
    best = {min((m for m in candidates.values() if m.kind == k), key=lambda m: m.manifest["val_loss"]).spec.slug
            for k in CANDIDATES}
    work = Path(tempfile.mkdtemp(prefix="bench_export_c_"))
    try:
        report(physics, [None, *candidates.values()], best, decoded[HOLDOUT], res[HOLDOUT], work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"\nload average now {os.getloadavg()[0]:.1f} (timings on a busy machine are slower)")


def report(physics, models, best: set[str], table, residual_table, work: Path) -> None:
    """One row per exported model: time per call, agreement with Python, footprint, estimate."""
    print(f"\nexported models (* the best of its kind by validation loss), run on the {table.height} rows of "
          f"{HOLDOUT}:")
    header = (f"{'model':42s} {'C us/call':>9s} {'Py us/sample':>12s} {'max|C-Py| N':>11s} {'N m':>8s} "
              f"{'flash B':>8s} {'flash %':>7s} {'RAM B':>6s} {'RAM %':>6s} {'M4 cycles (est.)':>16s} {'M4 us':>8s}")
    print(header + "\n" + "-" * len(header))
    ok = feat.usable(residual_table)
    f_phys, tau_phys = physics.extra_wrench(dynamics.flight_state(table, physics.vehicle))
    notes, verdicts = [], []
    for k, learned in enumerate(models):
        out = work / f"m{k}"
        exported = export_c.export_models(physics, learned, out, "bench")
        host = export_c.HostModel(out, exported.generated, work / f"build{k}")
        rows = export_c.input_rows(table, exported.fields)
        c = host.run(rows)
        c_us = host.seconds_per_call(rows) * 1e6
        f_py, tau_py = f_phys.copy(), tau_phys.copy()
        py, cycles, m4_us, label = "-", "-", "-", "physics only"
        if learned is not None:
            X = feat.matrix(residual_table, learned.feature_set)
            y = learned.predict_matrix(X)
            f_py, tau_py = f_py + y[:, :3], tau_py + y[:, 3:]
            py = f"{trainers.latency_us(learned.predict_one, X[0], 2000):.1f}"  # the learned part alone
            low, high, how = cycle_estimate(learned, X, arm_function_bytes(out, "quadcore_residual"))
            cycles, m4_us = f"{low:,.0f}-{high:,.0f}", f"{low / CLOCK_HZ * 1e6:.0f}-{high / CLOCK_HZ * 1e6:.0f}"
            star = "*" if learned.spec.slug in best else ""
            label = f"{star}physics + {learned.spec.slug} ({learned.feature_set.name})"
            notes.append(f"{label}: {exported.generated.learned}; {how}")
        f_err = np.abs(c["f_b_N"] - f_py)[ok].max()
        tau_err = np.abs(c["tau_b_Nm"] - tau_py)[ok].max()
        fp = exported.footprint
        flash, ram = (fp.flash_bytes, fp.ram_bytes) if fp else (0, 0)
        print(f"{label:42s} {c_us:9.3f} {py:>12s} {f_err:11.1e} {tau_err:8.1e} {flash:8d} "
              f"{flash / STM32F405_FLASH_BYTES:7.2%} {ram:6d} {ram / STM32F405_RAM_BYTES:6.2%} {cycles:>16s} "
              f"{m4_us:>8s}")
        verdicts += _verdicts(label, learned, best, c_us, flash, ram, f_err, tau_err)
    print("\nPy us/sample: LearnedModel.predict_one on one row (the learned part only; the physics has no "
          "per-sample path in Python).")
    print(f"footprint: {fp.target if fp else 'not measured'}.")
    print("M4 cycles: an ESTIMATE from operation counts, not a measurement (no Cortex-M4 here): "
          f"{SPLIT_CYCLES} cycles per tree split visited, {BISECT_CYCLES} per bisection step, {MAC_CYCLES} per "
          "multiply-add (low: cache hits, high: a flash wait-state miss), the physics part's instructions once to "
          "twice; libm's expf (motor_lag) not counted; M4 us at 168 MHz.")
    for n in notes:
        print(f"  {n}")
    print()
    for v in verdicts:
        print(v)


def _verdicts(label, learned, best, c_us, flash, ram, f_err, tau_err) -> list[str]:
    out = []
    if learned is not None and learned.kind == "xgboost" and learned.spec.slug in best:
        out.append(f"physics + best XGBoost: {c_us:.2f} us per call here: target < 5 us "
                   f"{'MET' if c_us < 5 else 'NOT MET'}")
    fits = flash <= 0.1 * STM32F405_FLASH_BYTES and ram <= 0.1 * STM32F405_RAM_BYTES
    out.append(f"{label}: flash {flash / STM32F405_FLASH_BYTES:.1%}, RAM {ram / STM32F405_RAM_BYTES:.2%} of the "
               f"STM32F405: within 10 % {'MET' if fits else 'NOT MET'}; C vs Python {f_err:.1e} N, {tau_err:.1e} N m: "
               f"< 1e-5 N and 1e-8 N m {'MET' if f_err < 1e-5 and tau_err < 1e-8 else 'NOT MET'}")
    return out


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    print(f"benchmark took {time.perf_counter() - t0:.0f} s")
