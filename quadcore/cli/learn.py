"""``quadcore train``: learn the residual the physics model leaves (XGBoost, MLP), evaluate, report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from quadcore import workflows
from quadcore.cli.base import UserError, progress, warn
from quadcore.cli.common import data_and_effects
from quadcore.learn import features as feat, learners, splits
from quadcore.learn.tables import TABLE_TITLES, text_table
from quadcore.workflows import fleet, learn


def cmd_train(args: argparse.Namespace) -> int:
    """Learn the residual the physics model leaves (XGBoost, MLP), evaluate, write the report."""
    data, names = data_and_effects(args)
    request = learn.LearningRequest(
        models=tuple(workflows.parse_names(args.models)), options={k: getattr(args, k, "") for k in learners.KINDS},
        loo=args.loo, compare=not args.no_compare, stride=args.stride, seed=args.seed, threads=args.threads,
        max_rows=args.max_rows)
    try:
        spec = workflows.resolve_model(args.model, args.vehicle, args.thrust_map, names)
        sets = feat.parse(args.feature_sets)
        request.learner_specs()  # a bad option fails before any decoding
    except (feat.FeatureError, learners.LearningError) as exc:
        raise UserError(str(exc)) from None
    csv_path = Path(args.flights_csv) if args.flights_csv else feat.find_flights_csv(data)
    if args.flights_csv and not (csv_path and csv_path.is_file()):
        raise UserError(f"flights CSV not found: {csv_path}")
    log = progress(args)

    flights = fleet.fleet_from_logs([str(data)], spec.vehicle, warn)
    try:
        holdout, note = learn.learning_holdout(args.holdout or splits.DEFAULT_HOLDOUT, flights.ids,
                                               explicit=args.holdout is not None)
    except learners.LearningError as exc:
        raise UserError(str(exc)) from None
    if note:
        print(f"note: {note}", file=sys.stderr)
    kinds = feat.read_flight_kinds(csv_path)
    if not kinds:
        print("note: no flights.csv (flight,kind): the training-size comparison (random vs preplanned) is skipped",
              file=sys.stderr)
    out = Path(args.out)
    try:
        done = learn.train_on_flights(flights, spec, sets, request, holdout, kinds, out, log)
    except learners.LearningError as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"cannot write to {out}: {exc}") from None
    report, paths = done.report, done.paths
    print(f"physics model: {done.physics.label}; held out: {holdout}; trained on {len(done.trained_on)} flights\n")
    for key in ("headline", "feature_sets", "training_size", "complexity", "lofo"):
        rows = report["tables"].get(key)
        if rows:
            print(f"{TABLE_TITLES[key]}:\n{text_table(rows)}\n")
    for n in report["notes"]:
        print(f"note: {n}")
    print(f"\n{report['verdict']}\n")
    print(f"report: {paths['html']} (and .md, .json)\nmodels: {out.resolve() / 'learned'}/<run>/\n"
          f"history: {len(report.get('history_files', []))} row(s) added under {out.resolve() / 'history'}")
    return 0
