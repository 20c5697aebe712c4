"""``quadcore export`` (flights as MCAP for Foxglove) and ``export-c`` (the model as C99)."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from quadcore.cli.base import UserError
from quadcore.cli.common import load_flights, main_tables, vehicle_of
from quadcore.export import c as export_c, mcap
from quadcore.learn import features as feat, learners
from quadcore.logs import flight as flightmod
from quadcore.physics import residuals
from quadcore.spec import model as modelmod


def cmd_export(args: argparse.Namespace) -> int:
    veh = vehicle_of(args)
    flights, _ = load_flights(args.paths, None)
    out = Path(args.out)
    try:
        given = flightmod.read_flight_starts(args.flights or feat.find_flights_csv(*map(Path, args.paths)))
        if args.start:
            given = {f.flight_id: flightmod.parse_start(args.start) for f in flights}
    except (ValueError, OSError) as exc:
        raise UserError(str(exc)) from None
    for fid, df in main_tables(flights, veh).items():
        table = residuals.residual_table(df, veh)
        fl = next(f for f in flights if f.flight_id == fid)
        flightmod.settle_start_time(fl, None, given.get(fid))
        start_ns = fl.provenance.start_ns
        if start_ns is None:  # decode_flight always estimates one; a flight built otherwise may not
            raise UserError(f"{fid}: no start time: give one with --start")
        counts = mcap.write_mcap(table, out / f"{fid}.mcap", start_ns, {"flight": fid, "vehicle": veh.name})
        print(f"{out / f'{fid}.mcap'}: {sum(counts.values())} messages on {len(counts)} topics")
    return 0


def cmd_export_c(args: argparse.Namespace) -> int:
    """The current model as C99 for a flight controller (see quadcore.export.c)."""
    if args.model_file:  # the plugin effects the model uses come from here, never from the saved model
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
