"""Learned residual models on the real flights: the best XGBoost and MLP trained on 18 flights,
jana02 held out, beside the study's figures.

    python benchmarks/bench_learning.py [LOGS_FOLDER]

"Best" is chosen by validation loss (validation flights drawn from the 18 training flights),
never by the held-out score, among a few candidates per kind. The chosen models are then
trained again for timing (best of 3), XGBoost with its default thread count (1) and with 2.

Targets (2-core machine): best XGBoost trained in < 10 s, MLP in < 60 s, per-sample prediction
of the tree model in Python < 100 us.
"""

import os
import sys
import time
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np
from _common import best_of, logs_folder

from quadcore.identify import model
from quadcore.learn import features as feat, learners, metrics, trainers
from quadcore.learn.tables import STUDY, text_table
from quadcore.logs import flight
from quadcore.physics import vehicle

HOLDOUT = "jana02"
CANDIDATES = {
    "xgboost": [replace(learners.default_spec("xgboost"), max_depth=d) for d in (2, 4, 6)],
    "mlp": [replace(learners.default_spec("mlp"), hidden=h) for h in ((), (64, 64))],
}
SETS = ("physics", "physics_rate", "full_state")
TARGETS = {"xgboost": 10.0, "mlp": 60.0}


def main() -> None:
    folder = logs_folder()
    veh = vehicle.load()
    nominal = model.PhysicsModel(veh, [])
    decoded = {f.flight_id: f.tables["fixedFrequency"] for f in map(flight.decode_flight, flight.discover_logs(folder))}
    if HOLDOUT not in decoded:
        print(f"{HOLDOUT} not among the logs in {folder}: nothing to compare with the study")
        sys.exit(0)
    res = {f: nominal.residual_table(df) for f, df in decoded.items()}
    kinds = feat.read_flight_kinds(feat.find_flights_csv(folder))
    train = sorted(f for f in res if f != HOLDOUT)
    tables = feat.feature_tables(res, [feat.FEATURE_SETS[s] for s in SETS])
    n_rows = sum(t.height for t in res.values())
    print(f"flights: {len(res)} (train {len(train)}, held out {HOLDOUT}), rows: {n_rows:,}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    cfg = learners.TrainConfig()
    print(f"fitting rows: every {cfg.stride}th sample; XGBoost threads {cfg.threads}, "
          f"torch threads {cfg.torch_threads}\n")

    print("selection by validation loss (standardised MSE on the validation flights):")
    best: dict[str, tuple] = {}
    for kind, specs in CANDIDATES.items():
        for spec in specs:
            for s in SETS:
                fs = feat.FEATURE_SETS[s]
                m = trainers.train(spec, fs, tables[s], train, cfg, nominal.to_dict(), kinds)
                print(f"  {kind:8s} {spec.slug:14s} {s:13s} val loss {m.manifest['val_loss']:.4f}  "
                      f"trained in {m.manifest['train_time_s']:6.2f} s")
                if kind not in best or m.manifest["val_loss"] < best[kind][0].manifest["val_loss"]:
                    best[kind] = (m, spec, fs)

    t = res[HOLDOUT]
    ok = feat.usable(t)
    y = feat.targets(t)[ok]
    rows: list[dict[str, Any]] = []
    verdicts: list[str] = []
    for kind, (m, spec, fs) in best.items():
        tabs = tables[fs.name]
        t_train, m = best_of(partial(trainers.train, spec, fs, tabs, train, cfg, nominal.to_dict(), kinds))
        extra = ""
        if kind == "xgboost":
            t_train2, _ = best_of(partial(trainers.train, spec, fs, tabs, train, replace(cfg, threads=2),
                                          nominal.to_dict(), kinds))
            extra = f" on {cfg.threads} thread(s) (on 2 threads: {t_train2:.2f} s)"
        X = feat.matrix(tabs[HOLDOUT], fs)[ok]
        p, t_pred = trainers.time_predict(m, X)
        lat = trainers.latency_us(m.predict_one, X[0], 2000)
        lat_lib = trainers.latency_us(m.predict_matrix, X[:1], 500)
        met = metrics.metrics(y, p)
        a = metrics.mae(met)
        study = STUDY[kind]
        rows.append({"model": study["label"], **{f"F{ax} MAE [N]": v for ax, v in zip("xyz", study["force_mae_N"])},
                     "train [s]": study["train_s"], "predict held-out [s]": study["predict_s"], "µs/sample": None,
                     "µs/sample (library)": None})
        rows.append({"model": f"ours: {kind} {spec.slug} ({fs.name})",
                     **{f"F{ax} MAE [N]": v for ax, v in zip("xyz", a[:3])},
                     "train [s]": t_train, "predict held-out [s]": t_pred,
                     "µs/sample": lat, "µs/sample (library)": lat_lib})
        verdicts.append(f"{kind} trained in {t_train:.2f} s{extra}: target < {TARGETS[kind]:g} s "
                        f"{'MET' if t_train < TARGETS[kind] else 'NOT MET'}")
        if kind == "xgboost":
            verdicts.append(f"xgboost per-sample prediction {lat:.1f} us (compiled NumPy forest; XGBoost's own "
                            f"inplace_predict on one row: {lat_lib:.0f} us): "
                            f"target < 100 us {'MET' if lat < 100 else 'NOT MET'}")
        else:
            verdicts.append(f"mlp per-sample prediction {lat:.1f} us (torch, (1, k) tensor, no_grad)")
        verdicts.append(f"  {kind} torque MAE [mN m]: " + " / ".join(f"{v * 1e3:.3f}" for v in a[3:])
                        + "; R² force " + " / ".join(f"{v:.2f}" for v in metrics.r2(met)[:3]))
    base = metrics.metrics(y, np.zeros_like(y))
    b = metrics.mae(base)
    rows.append({"model": "ours: physics-only (nominal, no learned correction)",
                 **{f"F{ax} MAE [N]": v for ax, v in zip("xyz", b[:3])}, "train [s]": None,
                 "predict held-out [s]": None, "µs/sample": None, "µs/sample (library)": None})
    mean = np.concatenate([feat.targets(res[f])[feat.usable(res[f])] for f in train]).mean(axis=0)
    tm = metrics.mae(metrics.metrics(y, np.broadcast_to(mean, y.shape)))
    rows.append({"model": "ours: training mean", **{f"F{ax} MAE [N]": v for ax, v in zip("xyz", tm[:3])},
                 "train [s]": None, "predict held-out [s]": None, "µs/sample": None, "µs/sample (library)": None})
    print(f"\nheld-out {HOLDOUT}, force MAE beside the study"
          " (the study's residual differs: see quadcore.learn.evaluation):")
    print(text_table(rows))
    print()
    for v in verdicts:
        print(v)
    print(f"\nload average now {os.getloadavg()[0]:.1f} (timings on a busy machine are slower)")


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    print(f"benchmark took {time.perf_counter() - t0:.0f} s")
