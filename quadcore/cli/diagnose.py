"""``quadcore diagnose``: where the model fails and which effect is missing (JSON, and a report)."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from quadcore.cli.base import output_folders, print_table, progress
from quadcore.cli.common import model_and_flights
from quadcore.commands import quadcore_command
from quadcore.identify.diagnosis import verdict
from quadcore.workflows import identify


def _discover_command(args: argparse.Namespace) -> str:
    """The ``quadcore discover`` command on the same flights and model as this ``diagnose``."""
    parts = [quadcore_command(), "discover", args.data, "--json", "discovery.json"]
    for flag, value in (("--model", args.model), ("--effects", args.effects), ("--vehicle", args.vehicle),
                        ("--thrust-map", args.thrust_map), ("--holdout", args.holdout), ("--sessions", args.sessions)):
        if value:
            parts += [flag, value]
    return shlex.join(parts)


def cmd_diagnose(args: argparse.Namespace) -> int:
    output_folders(str(Path(args.json).parent), args.report)
    spec, flights, holdout = model_and_flights(args)
    result = identify.diagnose(flights, spec, holdout, progress(args), where=args.data,
                               discover_command=_discover_command(args))
    out = identify.write_diagnosis_json(result, Path(args.json))
    b = result.baseline
    print(f"model: {result.model.label}  (evaluated by {result.evaluation.protocol})")
    print("baseline residual RMSE  force [N]: " + " ".join(f"{v:.4f}" for v in b.force_rmse_N)
          + "   torque [mN m]: " + " ".join(f"{v * 1e3:.4f}" for v in b.torque_rmse_Nm))
    print()
    print_table([[r["effect"], r["status"], r["target"], f"{r['explained']:.1%}", f"{r['above_noise']:.1%}",
                  f"{r['held_out_p']:.2g}", r["held_out_level"], r["why"]]
                 for r in verdict.candidate_summary(result.candidates)],
                ["candidate", "status", "target", "explained", "above noise", "held-out p", "held out in",
                 "why it is ranked here"])
    print("\nsmallest effect these flights would detect "
          f"({result.sensitivity_basis['detection_probability']:.0%} of the time):")
    print_table([[r["effect"], r["of"], "not in range" if r["undetected_below"] is None
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
