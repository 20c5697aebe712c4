"""``quadcore simulate``: closed-loop flights with known effects, as uSD logs and their ground truth."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from quadcore.cli.base import UserError, print_table
from quadcore.cli.common import vehicle_of
from quadcore.sim import simulation


def cmd_simulate(args: argparse.Namespace) -> int:
    """Simulate closed-loop flights with known effects: uSD logs + ``<log>.truth.json`` under --out."""
    veh = vehicle_of(args)
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
    print_table(rows, ["log", "kind", "duration s", "samples", "gaps", "truth"])
    out = Path(args.out).resolve()
    print(f"\n{len(written)} simulated log(s) in {out}; ground truth beside each log as <log>{simulation.TRUTH_SUFFIX}")
    return 0
