"""``quadcore vehicle``, ``residuals`` and ``fit-thrust``: the vehicle file and what the physics model
leaves on the flights."""

from __future__ import annotations

import argparse
from importlib import resources as package_files
from pathlib import Path

import numpy as np
import polars as pl

from quadcore.cli.base import UserError, print_table
from quadcore.cli.common import load_flights, main_tables, vehicle_of
from quadcore.commands import quadcore_command
from quadcore.physics import residuals, thrustfit, vehicle
from quadcore.store import store


def cmd_vehicle(args: argparse.Namespace) -> int:
    """``quadcore vehicle new NAME [--out FILE]``: a vehicle file from the commented template;
    ``quadcore vehicle check FILE``: load it as the pipeline would and print what it holds."""
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


def cmd_residuals(args: argparse.Namespace) -> int:
    veh = vehicle_of(args)
    flights, _ = load_flights(args.paths, None, log=lambda m: None)
    rows, all_tables = [], []
    for fid, df in main_tables(flights, veh).items():
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
    print_table(rows, ["flight", "rows", "Fx rmse", "Fy rmse", "Fz rmse", "Fz mean", "Fz/T mean",
                       "Tx rmse", "Ty rmse", "Tz rmse", "corr x", "corr y"])
    if args.out:
        print(f"\nresidual tables: {Path(args.out).resolve() / 'residuals'}/flight=*/data.parquet")
    return 0


def _residual_row(fid: str, table: pl.DataFrame) -> list[str]:
    s = residuals.summary(table)
    ok = table.filter(~pl.col("near_gap"))
    corr = [np.corrcoef(ok[f"f_res_b_{a}_N"], ok[f"v_b_{a}_mps"])[0, 1] for a in "xy"]
    weight = float(ok.select(pl.col("f_model_b_z_N").mean()).item() or 1.0)
    return [fid, str(table.height), *(f"{s[f'force_rmse_{a}_N']:.4f}" for a in "xyz"), f"{s['force_mean_z_N']:+.4f}",
            f"{s['force_mean_z_N'] / weight:+.1%}", *(f"{s[f'torque_rmse_{a}_Nm'] * 1e3:.3f}" for a in "xyz"),
            *(f"{c:+.2f}" for c in corr)]


def cmd_fit_thrust(args: argparse.Namespace) -> int:
    veh = vehicle_of(args)
    flights, _ = load_flights(args.paths, None, log=lambda m: None)
    tables = main_tables(flights, veh)
    missing = [fid for fid, df in tables.items() if "motor_1_radps" not in df.columns]
    if missing:
        raise UserError(f"no motor speed logged in {', '.join(missing)}: cannot fit f = k_F omega^2")
    try:
        k_F, per_flight = thrustfit.fit_k_F(tables, veh)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    print_table([[fid, f"{k:.4e}"] for fid, k in per_flight.items()] + [["ALL", f"{k_F:.4e}"]],
                ["flight", "k_F [N/(rad/s)^2]"])
    spread = np.std(list(per_flight.values())) / k_F
    print(f"\nk_F = {k_F:.4e} N/(rad/s)^2 (spread between flights {spread:.1%})")
    if spread > 0.05:
        print("warning: k_F differs between flights by more than 5%: the speed-to-thrust relation is not the "
              "same in all of them; consider fitting groups of flights separately")
    if args.write:
        src = Path(veh.source) if veh.source and not veh.source.startswith("builtin:") else None
        text = src.read_text() if src else package_files.files("quadcore").joinpath(
            f"vehicles/{vehicle.DEFAULT_VEHICLE}.toml").read_text()
        print(f"wrote {thrustfit.write_k_F(text, k_F, Path(args.write))}")
    return 0
