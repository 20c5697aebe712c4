"""What several command groups share and the numerical libraries load: the flights of the paths given, the
vehicle of ``--vehicle``/``--thrust-map``, the model and flights ``diagnose``/``discover``/``plan`` start from,
and the exceptions that mean "the user asked for something wrong"."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import polars as pl

from quadcore import effects, workflows
from quadcore.cli.base import UserError, warn
from quadcore.logs import flight as flightmod
from quadcore.physics import dynamics, vehicle
from quadcore.spec import model
from quadcore.spec.model import ModelSpec
from quadcore.workflows import fleet

# What main() prints in one line (exit code 2) instead of a traceback.
USER_ERRORS: tuple[type[Exception], ...] = (
    UserError, dynamics.UnusableFlightError, vehicle.VehicleFileError, model.ModelFileError,
    effects.UnknownEffectError, workflows.WorkflowError)


def load_flights(paths: list[str], out: Path | None = None,
                 log: Callable[[str], None] = print) -> tuple[list[flightmod.Flight], dict[str, str]]:
    """Decode every log under ``paths`` (:func:`quadcore.workflows.fleet.decode_logs`)."""
    return fleet.decode_logs(paths, out, log)


def vehicle_of(args: argparse.Namespace) -> vehicle.Vehicle:
    """The ``--vehicle`` file (default: the built-in one) with ``--thrust-map`` applied."""
    try:
        v = vehicle.load(args.vehicle)
        return v.with_thrust_map(args.thrust_map) if args.thrust_map else v
    except vehicle.VehicleFileError as exc:
        raise UserError(str(exc)) from None


def main_tables(flights: list[flightmod.Flight], veh: vehicle.Vehicle) -> dict[str, pl.DataFrame]:
    """The flights the physics can use with ``veh`` (:func:`quadcore.workflows.fleet.main_tables`;
    the skipped ones said on stderr): one bad flight never stops the others."""
    return dict(fleet.main_tables(flights, veh, warn=warn).tables)


def data_and_effects(args: argparse.Namespace) -> tuple[Path, list[str]]:
    """The DATA folder (which must exist) and the ``--effects`` names."""
    data = Path(args.data)
    if not data.exists():
        raise UserError(f"no such folder: {data}")
    return data, [n.strip() for n in (args.effects or "").split(",") if n.strip()]


def model_and_flights(args: argparse.Namespace) -> tuple[ModelSpec, fleet.Fleet, list[str]]:
    """The model (``--model`` file or ``--effects``, ``--sessions``), the usable flights of DATA
    and the ``--holdout`` names: what ``diagnose``, ``discover`` and ``plan`` start from."""
    data, names = data_and_effects(args)
    spec = workflows.resolve_model(args.model, args.vehicle, args.thrust_map, names, args.sessions)
    return spec, fleet.fleet_from_logs([str(data)], spec.vehicle, warn), workflows.parse_names(args.holdout)
