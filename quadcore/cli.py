"""The ``quadcore`` command: one command, one verb per stage.

    quadcore decode LOG_OR_FOLDER... --out DIR
    quadcore vehicle new NAME [--out FILE]     (a vehicle file of your own, every number commented)
    quadcore vehicle check FILE
    quadcore residuals LOG_OR_FOLDER... [--vehicle FILE] [--thrust-map KIND] [--out DIR]
    quadcore fit-thrust LOG_OR_FOLDER... [--vehicle FILE] [--write OUT.toml]
    quadcore export LOG_OR_FOLDER... --out DIR [--vehicle FILE]
    quadcore export-c MODEL_DIR_OR_FILE --out DIR [--learned xgboost|mlp|none] [--model-file MODEL.toml]
    quadcore train DATA [--holdout F] [--loo] [--models xgboost,mlp] [--feature-sets ...] [--effects ...] [--out DIR]
    quadcore diagnose DATA --json OUT.json [--vehicle FILE] [--effects e1,e2] [--holdout F1,F2] [--report DIR]
    quadcore discover DATA --json OUT.json [--model F] [--vehicle F] [--holdout F1,F2] [--sessions F]
                      [--write-effect DIR/NAME.py]
    quadcore plan DATA --json OUT.json --trajectory OUT.csv [--model F] [--vehicle F]
                  [--between A,B | --parameter EFFECT.NAME] [--arena XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX]
                  [--duration S] [--max-speed MPS] [--max-tilt DEG]
    quadcore simulate --out DIR [--kind KIND|default-set] [--duration S] [--flights N]
                      [--effect NAME:param=value,...] [--seed N] [--vehicle FILE]

User errors (missing paths, unreadable logs) print a clear message and exit
non-zero; they never end in a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

# Only the standard library at module level, and the quadcore modules that import nothing else (checked by
# tests/test_import_graph.py): `quadcore --help` must start in well under a second, so each command
# imports the numerical modules it needs.
from quadcore.commands import quadcore_command
from quadcore.learn import learners
from quadcore.store import ownership, safewrite

if TYPE_CHECKING:
    import polars as pl

    from quadcore.logs import flight as flightmod
    from quadcore.physics import vehicle

class UserError(Exception):
    """A mistake in what the user asked for: printed as a message, exit code 2."""


def _print_table(rows: list[list[str]], header: list[str]) -> None:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    for r in [header, ["-" * w for w in widths], *rows]:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)))


def load_flights(
    paths: list[str], out: Path | None = None, log=print
) -> tuple[list[flightmod.Flight], dict[str, str]]:
    """Decode every log under ``paths`` (:func:`quadcore.workflows.fleet.decode_logs`)."""
    from quadcore.workflows import fleet

    return fleet.decode_logs(paths, out, log)


def _output_folder(path: str) -> Path:
    """``path`` as an output folder: it must be a folder or not exist yet."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file, not a folder")
    return out


def cmd_decode(args: argparse.Namespace) -> int:
    out = _output_folder(args.out)
    flights, quarantined = load_flights(args.paths, out)
    events = sorted({e for f in flights for e in f.tables})
    rows = [[f.flight_id, *[str(f.provenance.rows.get(e, 0)) for e in events], str(len(f.warnings))]
            for f in flights]
    totals = ["TOTAL", *[str(sum(f.provenance.rows.get(e, 0) for f in flights)) for e in events],
              str(sum(len(f.warnings) for f in flights))]
    print()
    _print_table(rows + [totals], ["flight", *events, "warnings"])
    print(f"\n{len(flights)} flights decoded to {out.resolve() / 'decoded'}")
    for e in events:
        print(f"  {e}: {out.resolve() / 'decoded' / e}/flight=*/data.parquet")
    if quarantined:
        print(f"{len(quarantined)} file(s) quarantined (see {out.resolve() / 'quarantine'}):")
        for fid, reason in quarantined.items():
            print(f"  {fid}: {reason}")
    return 0 if flights else 1


def _vehicle(args: argparse.Namespace):
    from quadcore.physics import vehicle

    try:
        v = vehicle.load(args.vehicle)
        return v.with_thrust_map(args.thrust_map) if args.thrust_map else v
    except vehicle.VehicleFileError as exc:
        raise UserError(str(exc)) from None


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def _main_tables(flights: list[flightmod.Flight], veh: vehicle.Vehicle) -> dict[str, pl.DataFrame]:
    """The flights the physics can use with ``veh`` (:func:`quadcore.workflows.fleet.main_tables`;
    the skipped ones said on stderr): one bad flight never stops the others."""
    from quadcore.workflows import fleet

    return dict(fleet.main_tables(flights, veh, warn=_warn).tables)


def cmd_residuals(args: argparse.Namespace) -> int:
    import polars as pl

    from quadcore.physics import residuals, vehicle
    from quadcore.store import store

    veh = _vehicle(args)
    flights, _ = load_flights(args.paths, None, log=lambda m: None)
    rows, all_tables = [], []
    for fid, df in _main_tables(flights, veh).items():
        try:
            table = residuals.residual_table(df, veh)
        except vehicle.VehicleFileError as exc:
            raise UserError(str(exc)) from None
        if args.out:
            store.write_parquet(table, store.table_path(Path(args.out), "residuals", fid),
                                {"flight": fid, "vehicle": veh.name, "units": residuals.column_units(table)})
        all_tables.append(table.with_columns(pl.lit(fid).alias("flight")))
        rows.append(_residual_row(fid, table))
    rows.append(_residual_row("ALL", pl.concat(all_tables)))
    print(f"vehicle: {veh.name} ({veh.source}), thrust map: {veh.thrust_map_kind}")
    print("force residual f_res_b in N, torque residual tau_res_b in mN m; corr = corr(f_res_b, v_b) per axis\n")
    _print_table(rows, ["flight", "rows", "Fx rmse", "Fy rmse", "Fz rmse", "Fz mean", "Fz/T mean",
                        "Tx rmse", "Ty rmse", "Tz rmse", "corr x", "corr y"])
    if args.out:
        print(f"\nresidual tables: {Path(args.out).resolve() / 'residuals'}/flight=*/data.parquet")
    return 0


def _residual_row(fid: str, table: pl.DataFrame) -> list[str]:
    import numpy as np
    import polars as pl

    from quadcore.physics import residuals

    s = residuals.summary(table)
    ok = table.filter(~pl.col("near_gap"))
    corr = [np.corrcoef(ok[f"f_res_b_{a}_N"], ok[f"v_b_{a}_mps"])[0, 1] for a in "xy"]
    weight = float(ok.select(pl.col("f_model_b_z_N").mean()).item() or 1.0)
    return [fid, str(table.height), *(f"{s[f'force_rmse_{a}_N']:.4f}" for a in "xyz"), f"{s['force_mean_z_N']:+.4f}",
            f"{s['force_mean_z_N'] / weight:+.1%}", *(f"{s[f'torque_rmse_{a}_Nm'] * 1e3:.3f}" for a in "xyz"),
            *(f"{c:+.2f}" for c in corr)]


def cmd_fit_thrust(args: argparse.Namespace) -> int:
    from importlib import resources

    import numpy as np

    from quadcore.physics import thrustfit, vehicle

    veh = _vehicle(args)
    flights, _ = load_flights(args.paths, None, log=lambda m: None)
    tables = _main_tables(flights, veh)
    missing = [fid for fid, df in tables.items() if "motor_1_radps" not in df.columns]
    if missing:
        raise UserError(f"no motor speed logged in {', '.join(missing)}: cannot fit f = k_F omega^2")
    try:
        k_F, per_flight = thrustfit.fit_k_F(tables, veh)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    _print_table([[fid, f"{k:.4e}"] for fid, k in per_flight.items()] + [["ALL", f"{k_F:.4e}"]],
                 ["flight", "k_F [N/(rad/s)^2]"])
    spread = np.std(list(per_flight.values())) / k_F
    print(f"\nk_F = {k_F:.4e} N/(rad/s)^2 (spread between flights {spread:.1%})")
    if spread > 0.05:
        print("warning: k_F differs between flights by more than 5%: the speed-to-thrust relation is not the "
              "same in all of them; consider fitting groups of flights separately")
    if args.write:
        src = Path(veh.source) if veh.source and not veh.source.startswith("builtin:") else None
        text = src.read_text() if src else resources.files("quadcore").joinpath(
            f"vehicles/{vehicle.DEFAULT_VEHICLE}.toml").read_text()
        print(f"wrote {thrustfit.write_k_F(text, k_F, Path(args.write))}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Simulate closed-loop flights with known effects: uSD logs + ``<log>.truth.json`` under --out."""
    from dataclasses import replace

    from quadcore.sim import simulation

    veh = _vehicle(args)
    try:
        effects: dict[str, dict[str, float]] = {}
        for spec in args.effect or []:
            name, params = simulation.parse_effect_spec(spec)
            if name in effects:
                raise simulation.SimulationError(f"effect {name!r} given twice; put all its parameters in one --effect")
            effects[name] = params
        if args.flights is not None and args.flights < 1:
            raise simulation.SimulationError("--flights must be at least 1")
        if args.kind == "default-set":
            configs = simulation.default_flights(args.seed)
            n = args.flights or len(configs)
            configs = [replace(configs[i % len(configs)], seed=args.seed + i) for i in range(n)]
        else:
            configs = [simulation.SimConfig(kind=args.kind, seed=args.seed + i) for i in range(args.flights or 1)]
        if args.duration is not None:
            configs = [replace(c, duration_s=args.duration) for c in configs]
        for c in configs:
            c.validate()
        written = simulation.simulate_set(args.out, configs, effects, veh)
    except simulation.SimulationError as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"cannot write to {args.out}: {exc}") from None
    rows = []
    for (log_path, truth_path), cfg in zip(written, configs):
        truth = simulation.read_truth(log_path)
        rows.append([log_path.name, cfg.kind, f"{truth['duration_s']:.1f}", str(truth["samples"]), str(truth["gaps"]),
                     truth_path.name])
    print(f"vehicle: {veh.name} ({veh.source}); effects: "
          + (", ".join(f"{n}({', '.join(f'{k}={v:g}' for k, v in p.items())})" for n, p in effects.items()) or "none"))
    _print_table(rows, ["log", "kind", "duration s", "samples", "gaps", "truth"])
    out = Path(args.out).resolve()
    print(f"\n{len(written)} simulated log(s) in {out}; ground truth beside each log as <log>{simulation.TRUTH_SUFFIX}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from quadcore.export import mcap as export
    from quadcore.logs import flight as flightmod
    from quadcore.physics import residuals

    veh = _vehicle(args)
    flights, _ = load_flights(args.paths, None)
    out = Path(args.out)
    from quadcore.learn import features as feat

    try:
        given = flightmod.read_flight_starts(args.flights or feat.find_flights_csv(*map(Path, args.paths)))
        if args.start:
            given = {f.flight_id: flightmod.parse_start(args.start) for f in flights}
    except (ValueError, OSError) as exc:
        raise UserError(str(exc)) from None
    for fid, df in _main_tables(flights, veh).items():
        table = residuals.residual_table(df, veh)
        fl = next(f for f in flights if f.flight_id == fid)
        flightmod.settle_start_time(fl, None, given.get(fid))
        start_ns = fl.provenance.start_ns
        if start_ns is None:  # decode_flight always estimates one; a flight built otherwise may not
            raise UserError(f"{fid}: no start time: give one with --start")
        counts = export.write_mcap(table, out / f"{fid}.mcap", start_ns, {"flight": fid, "vehicle": veh.name})
        print(f"{out / f'{fid}.mcap'}: {sum(counts.values())} messages on {len(counts)} topics")
    return 0


def cmd_export_c(args: argparse.Namespace) -> int:
    """The current model as C99 for a flight controller (see quadcore.export.c)."""
    from quadcore.export import c as export_c

    if args.model_file:  # the plugin effects the model uses come from here, never from the saved model
        from quadcore.spec import model as modelmod

        modelmod.load_model_file(args.model_file)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            exported = export_c.export(args.model, args.out, args.learned)
    except (export_c.ExportError, learners.LearningError) as exc:
        raise UserError(str(exc)) from None
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    g = exported.generated
    print(f"model: {g.label}")
    print(f"inputs: {', '.join(f.name for f in g.fields) or 'none'}" + (f"; features: {', '.join(g.feature_columns)}"
                                                                          if g.feature_columns else ""))
    fp = exported.footprint
    print(fp.comment().replace("\n", " ") if fp else "footprint: not measured (no C compiler)")
    print(f"wrote {exported.header} and {exported.source}")
    return 0


def _data_and_effects(args: argparse.Namespace) -> tuple[Path, list[str]]:
    """The DATA folder (which must exist) and the ``--effects`` names."""
    data = Path(args.data)
    if not data.exists():
        raise UserError(f"no such folder: {data}")
    return data, [n.strip() for n in (args.effects or "").split(",") if n.strip()]


def _model_and_flights(args: argparse.Namespace):
    """The model (``--model`` file or ``--effects``, ``--sessions``), the usable flights of DATA
    and the ``--holdout`` names: what ``diagnose`` and ``discover`` start from."""
    from quadcore import workflows
    from quadcore.workflows import fleet

    data, names = _data_and_effects(args)
    spec = workflows.resolve_model(args.model, args.vehicle, args.thrust_map, names, args.sessions)
    return spec, fleet.fleet_from_logs([str(data)], spec.vehicle, _warn), workflows.parse_names(args.holdout)


def _output_folders(*paths: str | None) -> None:
    """Make the folders the outputs go to now, so that one that cannot be made (a file in the
    way, no permission) stops the command before the work, not after it (``OSError``: one line)."""
    for path in paths:
        if path:
            Path(path).mkdir(parents=True, exist_ok=True)


def _progress(args: argparse.Namespace):
    return (lambda m: print(m, file=sys.stderr)) if not args.quiet else (lambda m: None)


def _discover_command(args: argparse.Namespace) -> str:
    """The ``quadcore discover`` command on the same flights and model as this ``diagnose``."""
    import shlex

    parts = [quadcore_command(), "discover", args.data, "--json", "discovery.json"]
    for flag, value in (("--model", args.model), ("--effects", args.effects), ("--vehicle", args.vehicle),
                        ("--thrust-map", args.thrust_map), ("--holdout", args.holdout), ("--sessions", args.sessions)):
        if value:
            parts += [flag, value]
    return shlex.join(parts)


def cmd_diagnose(args: argparse.Namespace) -> int:
    from quadcore.identify.diagnosis import verdict
    from quadcore.workflows import identify

    _output_folders(str(Path(args.json).parent), args.report)
    spec, flights, holdout = _model_and_flights(args)
    result = identify.diagnose(flights, spec, holdout, _progress(args), where=args.data,
                               discover_command=_discover_command(args))
    out = identify.write_diagnosis_json(result, Path(args.json))
    b = result.baseline
    print(f"model: {result.model.label}  (evaluated by {result.evaluation.protocol})")
    print("baseline residual RMSE  force [N]: " + " ".join(f"{v:.4f}" for v in b.force_rmse_N)
          + "   torque [mN m]: " + " ".join(f"{v * 1e3:.4f}" for v in b.torque_rmse_Nm))
    print()
    _print_table([[r["effect"], r["status"], r["target"], f"{r['explained']:.1%}", f"{r['above_noise']:.1%}",
                   f"{r['held_out_p']:.2g}", r["why"]] for r in verdict.candidate_summary(result.candidates)],
                 ["candidate", "status", "target", "explained", "above noise", "held-out p", "why it is ranked here"])
    print("\nsmallest effect these flights would detect "
          f"({result.sensitivity_basis['detection_probability']:.0%} of the time):")
    _print_table([[r["effect"], r["of"], "not in range" if r["undetected_below"] is None
                   else f"{r['undetected_below']:.2g} {r['unit']}"]
                  for r in verdict.sensitivity_rows(result.sensitivity, result.sensitivity_basis)],
                 ["effect", "parameter", "undetected below"])
    for d in result.disagreements:
        print(f"\n{d.effect}.{d.parameter} differs between groups of flights ({d.source}):")
        for g in d.groups:
            print(f"  {g.value:.4g} ± {g.std:.2g}: {', '.join(g.flights)}")
        for note in d.notes:
            print(f"  note: {note}")
    print(f"\n{result.verdict}\n\nwrote {out}")  # the verdict says how stable its answer is, and the protocol
    if args.report:
        md, page = identify.write_diagnosis_report(result, Path(args.report), model_file=spec.source)
        with_discovery = identify.discovery_for(args.report, spec.effects) is not None
        first = f"{quadcore_command()} discover ... --json {Path(args.report) / 'discovery.json'}"
        print(f"wrote {md} and {page}" + ("" if with_discovery else
              f" (no discovery section: run `{first}` with the same model first to include one)"))
    return 0


def _rmse_line(label: str, d: dict) -> str:
    return (f"{label} force [N]: " + " ".join(f"{v:.4f}" for v in d["force_rmse_N"])
            + "   torque [mN m]: " + " ".join(f"{v * 1e3:.4f}" for v in d["torque_rmse_Nm"]))


def cmd_discover(args: argparse.Namespace) -> int:
    """Terms the effect library lacks: sparse regression of the residual on candidate terms."""
    from quadcore.identify import discovery
    from quadcore.workflows import identify

    if args.write_effect:
        target = Path(args.write_effect)
        if target.suffix != ".py" or not discovery.NAME_RE.match(target.stem):
            raise UserError(f"--write-effect needs DIR/NAME.py with NAME a Python identifier, got {target}")
    _output_folders(str(Path(args.json).parent), str(Path(args.write_effect).parent) if args.write_effect else None)
    spec, flights, holdout = _model_and_flights(args)
    result = identify.discover(flights, spec, holdout, _progress(args), where=args.data)
    out = Path(args.json)
    try:
        identify.write_discovery(result, out)
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc}") from None
    ev = result.evaluation
    print(f"model: {'+'.join(['nominal', *spec.effects])}  ({ev['mode']}, {len(ev['eval_flights'])} flights evaluated)")
    print(_rmse_line("held-out residual RMSE before", result.baseline))
    print(_rmse_line("held-out residual RMSE after ", result.after))
    print()
    print(result.summary)
    for a in result.axes:
        for note in a.notes:
            print(f"note ({a.target}): {note}")
    for t in result.terms:
        if t.matches_effects or t.collinear_with:
            print(f"  {t.target} {t.expression}: "
                  + "; ".join(filter(None, [
                      f"matches {', '.join(t.matches_effects)}" if t.matches_effects else "",
                      f"collinear with {', '.join(t.collinear_with[:4])}" if t.collinear_with else ""])))
    print(f"\nwrote {out}")
    if args.write_effect:
        try:
            written = discovery.write_effect(result, Path(args.write_effect), spec.vehicle)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        for term, why in written.left_out.items():
            print(f"left out of {written.path.name}: {term}: {why}")
        print(f"wrote {written.path}: add it to the model file's plugins and its name ({written.path.stem}) to effects")
    return 0


def cmd_plan(args: argparse.Namespace) -> int:
    """The flight that separates what the diagnosis cannot tell apart (``docs/flight-planning.md``)."""
    from quadcore.workflows import identify, plan as planflow

    request = _plan_request(args)
    _output_folders(str(Path(args.json).parent), str(Path(args.trajectory).parent))
    spec, flights, holdout = _model_and_flights(args)
    diag = identify.diagnose(flights, spec, holdout, _progress(args), where=args.data)
    from quadcore.plan import limits, question

    try:
        result = planflow.plan(flights, spec, diag, request, _progress(args))
    except (question.QuestionError, limits.LimitsError) as exc:
        raise UserError(str(exc)) from None
    written = planflow.write(result, Path(args.json), Path(args.trajectory))
    if not result.planned:
        print(f"nothing to plan: {result.question.why}\nwrote {written.json}")
        return 0
    pred = result.predicted()
    print(f"question: {result.question.why}")
    print(f"manoeuvre: {result.manoeuvre.describe() if result.manoeuvre else ''} ({result.duration_s:g} s, "
          f"{len(result.trajectory.durations) if result.trajectory is not None else 0} pieces)")
    for k, v in pred.items():
        print(f"  {k}: {'n/a' if v is None else f'{v:.3g}'}")
    if result.design.get("expected_to_decide") is False:
        print("  note: the best flight of the family is not predicted to break the tie with margin "
              f"(objective {result.design['after']['value']:.2f} < 1); see docs/flight-planning.md")
    for f in result.proof:
        print(f"  flown with {f.truth} true: diagnosis ranks {f.top} first"
              + (f", tied with {', '.join(f.tied_with)}" if f.tied_with else ", no tie")
              + (f"; separation {f.sigma:.1f} σ" if f.sigma is not None else ""))
    print(f"wrote {written.trajectory}, {written.plot} and {written.json}")
    return 0


def _plan_request(args: argparse.Namespace):
    """The plan's question, limits and flight time from the command line (``UserError`` if bad)."""
    from quadcore.plan import limits, planner

    between = None
    if args.between:
        names = [n.strip() for n in args.between.split(",") if n.strip()]
        if len(names) != 2:
            raise UserError(f"--between needs two effects A,B, got {args.between!r}")
        between = (names[0], names[1])
    if args.parameter and "." not in args.parameter:
        raise UserError(f"--parameter needs EFFECT.NAME, got {args.parameter!r}")
    try:
        arena = tuple(float(v) for v in args.arena.split(",")) if args.arena else limits.DEFAULT_ARENA
        lim = limits.Limits(args.max_speed, args.max_tilt, None, arena)  # type: ignore[arg-type]
    except ValueError as exc:
        raise UserError(f"bad limits: {exc}") from None
    if not 2.0 <= args.duration <= 120.0:
        raise UserError("--duration must be between 2 and 120 s")
    return planner.PlanRequest(between, args.parameter or None, lim, args.duration, not args.no_proof, args.seed)


def cmd_train(args: argparse.Namespace) -> int:
    """Learn the residual the physics model leaves (XGBoost, MLP), evaluate, write the report."""
    from quadcore import workflows
    from quadcore.learn import features as feat, splits
    from quadcore.learn.tables import TABLE_TITLES, text_table
    from quadcore.workflows import fleet, learn

    data, names = _data_and_effects(args)
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
    log = (lambda m: print(m, file=sys.stderr)) if not args.quiet else (lambda m: None)

    flights = fleet.fleet_from_logs([str(data)], spec.vehicle, _warn)
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


def cmd_vehicle(args: argparse.Namespace) -> int:
    """``quadcore vehicle new NAME [--out FILE]``: a vehicle file from the commented template;
    ``quadcore vehicle check FILE``: load it as the pipeline would and print what it holds."""
    from quadcore.physics import vehicle

    if args.action == "new":
        out = Path(args.out or f"{args.name}.toml")
        v = vehicle.write_template(args.name, out)
        print(f"wrote {out}: vehicle {v.name!r} with the Crazyflie 2.1's numbers; replace each with yours (every "
              f"line says its meaning and unit), then check it with `{quadcore_command()} vehicle check {out}`")
        return 0
    v = vehicle.load(Path(args.name))
    print(f"{args.name}: vehicle {v.name!r}, {v.mass_kg * 1e3:.4g} g, {v.n_rotors} rotors, thrust map "
          f"{v.thrust_map_kind}, hover thrust per rotor {v.weight_N / v.n_rotors * 1e3:.4g} mN")
    print("it is valid; use it with vehicle = \"PATH\" in the model file (PATH relative to the model file), "
          f"--vehicle {args.name} (CLI) or QUADCORE_VEHICLE={args.name} (pipeline)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    # one flat table of the verbs and their options, read top to bottom: long, not deep (issue #15)
    parser = argparse.ArgumentParser(prog="quadcore",
                                     description="Quadrotor flight logs -> SI Parquet -> dynamics models.")
    sub = parser.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("decode", help="decode uSD logs into SI Parquet")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--out", required=True, metavar="DIR", help="output data root")
    p.set_defaults(func=cmd_decode)

    def vehicle_args(p):
        p.add_argument("--vehicle", default=None, metavar="FILE", help="vehicle TOML (default: built-in Crazyflie 2.1)")
        p.add_argument("--thrust-map", default=None, metavar="KIND",
                       help="override the vehicle file's thrust map (pwm_vbat or motor_speed)")

    p = sub.add_parser("vehicle", help="a vehicle file of your own: write one from the commented template, or "
                       "check one")
    p.add_argument("action", choices=["new", "check"], help="new: write a template; check: load and summarise FILE")
    p.add_argument("name", metavar="NAME_OR_FILE", help="new: the vehicle's name; check: the vehicle file")
    p.add_argument("--out", default=None, metavar="FILE", help="new: where to write it (default NAME.toml)")
    p.set_defaults(func=cmd_vehicle)

    p = sub.add_parser("residuals", help="residual force and torque statistics per flight")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--out", default=None, metavar="DIR", help="also write residual Parquet under DIR/residuals")
    vehicle_args(p)
    p.set_defaults(func=cmd_residuals)

    p = sub.add_parser("fit-thrust", help="fit k_F of the motor-speed thrust map f = k_F omega^2")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--write", default=None, metavar="OUT.toml", help="write a vehicle file with the fitted k_F")
    vehicle_args(p)
    p.set_defaults(func=cmd_fit_thrust)

    p = sub.add_parser("simulate", help="simulate flights with known effects as uSD logs + ground truth JSON")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the logs (sim000, ...) and <log>.truth.json")
    p.add_argument("--kind", default="default-set",
                   choices=["figure8", "circle0", "yaw0", "random", "hover", "low_pass", "default-set"],
                   help="what to fly (default: the default set of 6 varied flights)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="flight length in seconds")
    p.add_argument("--flights", type=int, default=None, metavar="N", help="number of flights (seeds SEED, SEED+1, ...)")
    p.add_argument("--effect", action="extend", nargs="+", default=None, metavar="NAME:param=value,...",
                   help="an effect to switch on, e.g. rotor_drag:k_x_s_per_m=0.4,k_y_s_per_m=0.4 (repeatable)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (default 0)")
    p.add_argument("--vehicle", default=None, metavar="FILE", help="vehicle TOML (default: built-in Crazyflie 2.1)")
    p.set_defaults(func=cmd_simulate, thrust_map=None)

    p = sub.add_parser("export", help="flights as MCAP for Foxglove (pose, IMU, motors, model vs measured)")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--start", metavar="ISO_TIME", help="the flight's start (UTC, e.g. 2024-05-01T12:00:00Z); default: "
                   "the flights file's start_utc, else the log file's modification time taken as the end of the flight")
    p.add_argument("--flights", metavar="FLIGHTS.csv", help="flights file with a start_utc column "
                   "(default: flights.csv beside or above the logs)")
    vehicle_args(p)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("export-c", help="the model as C99 for a flight controller (header + source), checked")
    p.add_argument("model", metavar="MODEL_DIR_OR_FILE",
                   help="a learned model folder, a physics_model.json, or a data root (its best learned model)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for quadcore_model.h and quadcore_model.c")
    p.add_argument("--learned", default="xgboost", choices=["xgboost", "mlp", "none"],
                   help="from a data root: the best model of this kind (default xgboost), or none (physics only)")
    p.add_argument("--model-file", default=None, metavar="MODEL.toml",
                   help="the model file whose plugins the model's plugin effects come from (a saved model never "
                        "names code to run: its plugins are checked against these by name and SHA-256)")
    p.set_defaults(func=cmd_export_c)

    p = sub.add_parser("diagnose", help="where the model fails and which effect is missing (JSON report)")
    p.add_argument("data", metavar="DATA", help="a folder of raw uSD logs")
    p.add_argument("--json", required=True, metavar="OUT.json")
    p.add_argument("--effects", default="", metavar="e1,e2,...", help="effects in the model (default: none, "
                   "or the model file's)")
    p.add_argument("--model", default=None, metavar="MODEL.toml", help="a model file (vehicle, effects, plugins)")
    p.add_argument("--holdout", default="", metavar="FLIGHT,...", help="score on these flights (default: "
                   "cross-validation over flights)")
    p.add_argument("--report", default=None, metavar="DIR", help="also write diagnosis.md and diagnosis.html")
    p.add_argument("--sessions", default=None, metavar="SESSIONS.toml", help="groups of flights ([sessions] NAME = "
                   "[\"flight\", \"pattern*\"]) whose parameters may differ (default: groups found from the data)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    vehicle_args(p)
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("discover", help="terms the effect library lacks: sparse regression on the residual (JSON)")
    p.add_argument("data", metavar="DATA", help="a folder of raw uSD logs")
    p.add_argument("--json", required=True, metavar="OUT.json")
    p.add_argument("--model", default=None, metavar="MODEL.toml", help="a model file: discover on top of its effects")
    p.add_argument("--effects", default="", metavar="e1,e2,...", help="effects in the model (instead of the file's)")
    p.add_argument("--holdout", default="", metavar="FLIGHT,...", help="score on these flights (default: "
                   "cross-validation over flights)")
    p.add_argument("--write-effect", default=None, metavar="DIR/NAME.py",
                   help="write the kept terms as a linear effect plugin module NAME")
    p.add_argument("--sessions", default=None, metavar="SESSIONS.toml", help="groups of flights for the model's "
                   "per-session effects, as in diagnose (default: the model file's, else found from the data)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    vehicle_args(p)
    p.set_defaults(func=cmd_discover)

    p = sub.add_parser("plan", help="the next flight: a trajectory that separates what the data cannot tell apart")
    p.add_argument("data", metavar="DATA", help="a folder of raw uSD logs")
    p.add_argument("--json", required=True, metavar="OUT.json", help="the plan (and OUT.png, its picture)")
    p.add_argument("--trajectory", required=True, metavar="OUT.csv", help="the trajectory in the lab's format")
    p.add_argument("--model", default=None, metavar="MODEL.toml", help="a model file (vehicle, effects, plugins)")
    p.add_argument("--effects", default="", metavar="e1,e2,...", help="effects in the model (instead of the file's)")
    p.add_argument("--between", default="", metavar="A,B", help="separate these two candidates")
    p.add_argument("--parameter", default="", metavar="EFFECT.NAME", help="pin down this parameter")
    p.add_argument("--arena", default="", metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                   help="the room the flight must stay in, m (default -1,-1,0.2,1,1,1.5)")
    p.add_argument("--duration", type=float, default=20.0, metavar="S", help="manoeuvre time, s (default 20)")
    p.add_argument("--max-speed", type=float, default=1.5, metavar="MPS", help="default 1.5 m/s")
    p.add_argument("--max-tilt", type=float, default=25.0, metavar="DEG", help="default 25 degrees")
    p.add_argument("--holdout", default="", metavar="FLIGHT,...", help="as in diagnose")
    p.add_argument("--sessions", default=None, metavar="SESSIONS.toml", help="as in diagnose")
    p.add_argument("--no-proof", action="store_true", help="skip flying the plan in the simulator")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="the proof's simulator seed")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    vehicle_args(p)
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("train", help="learn the residual the physics model leaves (XGBoost, MLP) and report")
    p.add_argument("data", metavar="DATA", help="a folder of raw uSD logs")
    p.add_argument("--holdout", default=None, metavar="FLIGHT",
                   help="the held-out flight (default jana02, or the last flight when there is no jana02)")
    p.add_argument("--loo", action="store_true", help="also leave-one-flight-out cross-validation over all flights")
    p.add_argument("--models", default="xgboost,mlp", metavar="KIND,...", help="model kinds (default xgboost,mlp)")
    p.add_argument("--xgboost", default="", metavar="OPTS", help="XGBoost options, e.g. depth=4,trees=300,eta=0.1")
    p.add_argument("--mlp", default="", metavar="OPTS", help="MLP options, e.g. hidden=64x64,epochs=100,lr=0.001")
    p.add_argument("--feature-sets", default="", metavar="SET,...",
                   help="feature sets (default: all built-in; define one as name=col1+col2+...)")
    p.add_argument("--effects", default="", metavar="e1,e2,...",
                   help="effects in the physics model, fitted on the training flights (default: none)")
    p.add_argument("--model", default=None, metavar="MODEL.toml",
                   help="a model file (vehicle, effects, plugins) for the physics model under the learned ones")
    p.add_argument("--out", default="data", metavar="DIR",
                   help="data root for learned/, reports/, history/ (default: data)")
    p.add_argument("--flights-csv", default=None, metavar="FILE",
                   help="flight kinds (flight,kind; default: flights.csv beside or above DATA)")
    p.add_argument("--no-compare", action="store_true", help="skip the training-size and complexity comparisons")
    p.add_argument("--stride", type=int, default=5, metavar="N", help="fit on every N-th sample (default 5)")
    p.add_argument("--max-rows", type=int, default=learners.DEFAULT_ROW_BUDGET, metavar="N",
                   help=f"the row budget: the most usable training rows one model holds; above it they are drawn "
                        f"evenly per flight (default {learners.DEFAULT_ROW_BUDGET})")
    p.add_argument("--seed", type=int, default=0, metavar="N")
    p.add_argument("--threads", type=int, default=1, metavar="N",
                   help="XGBoost threads (default 1, measured faster here)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    vehicle_args(p)
    p.set_defaults(func=cmd_train)
    return parser


def _user_errors() -> tuple[type[Exception], ...]:
    """The exceptions that mean "the user asked for something wrong" (imported only once a
    command has run, so that ``--help`` stays fast)."""
    from quadcore import effects, workflows
    from quadcore.physics import dynamics, vehicle
    from quadcore.spec import model

    return (UserError, dynamics.UnusableFlightError, vehicle.VehicleFileError, model.ModelFileError,
            effects.UnknownEffectError, workflows.WorkflowError)


# Verbs that write a data root (``--out``): they hold its lock, so that two jobs on one root wait
# for each other instead of interleaving, and sweep what killed runs left there.
DATA_ROOT_VERBS = ("decode", "train")


@contextlib.contextmanager
def _data_root_held(args: argparse.Namespace):
    if args.verb not in DATA_ROOT_VERBS:
        yield
        return
    out = _output_folder(args.out)
    created = not out.exists()
    try:  # a folder quadcore did not make is refused before anything is written there
        note = ownership.claim(out, "--out")
    except ownership.ForeignFolderError as exc:
        raise UserError(str(exc)) from None
    if note:
        print(f"note: {note}", file=sys.stderr)
    try:
        with safewrite.data_root_lock(out, on_wait=lambda m: print(m, file=sys.stderr)):
            safewrite.sweep_stale(out)
            yield
    finally:
        # a command that wrote nothing leaves no folder; one that could not create it keeps its own error
        own = {safewrite.LOCK_FILE, ownership.MARKER}
        if created and out.is_dir() and {p.name for p in out.iterdir()} <= own:
            for name in own:
                (out / name).unlink(missing_ok=True)
            out.rmdir()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with _data_root_held(args):
            return args.func(args)
    except OSError as exc:  # a folder that cannot be written, a file where a folder should be, ...
        print(f"quadcore {args.verb}: error: {exc.strerror or exc}: {exc.filename or ''}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # commands return their code: this came from user code (a plugin)
        print(f"quadcore {args.verb}: error: code run by the command (an effect plugin?) called "
              f"exit({exc.code!r}); the command did not finish", file=sys.stderr)
        return 2
    except Exception as exc:
        if not isinstance(exc, _user_errors()):
            raise
        print(f"quadcore {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
