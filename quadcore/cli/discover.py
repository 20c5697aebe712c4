"""``quadcore discover``: terms the effect library lacks, by sparse regression on the residual (its own
group: the term selection loads scikit-learn, which ``diagnose`` does not need)."""

from __future__ import annotations

import argparse
from pathlib import Path

from quadcore.cli.base import UserError, output_folders, progress
from quadcore.cli.common import model_and_flights
from quadcore.identify import discovery
from quadcore.workflows import identify


def _rmse_line(label: str, d: dict) -> str:
    return (f"{label} force [N]: " + " ".join(f"{v:.4f}" for v in d["force_rmse_N"])
            + "   torque [mN m]: " + " ".join(f"{v * 1e3:.4f}" for v in d["torque_rmse_Nm"]))


def cmd_discover(args: argparse.Namespace) -> int:
    """Terms the effect library lacks: sparse regression of the residual on candidate terms."""
    if args.write_effect:
        target = Path(args.write_effect)
        if target.suffix != ".py" or not discovery.NAME_RE.match(target.stem):
            raise UserError(f"--write-effect needs DIR/NAME.py with NAME a Python identifier, got {target}")
    output_folders(str(Path(args.json).parent), str(Path(args.write_effect).parent) if args.write_effect else None)
    spec, flights, holdout = model_and_flights(args)
    result = identify.discover(flights, spec, holdout, progress(args), where=args.data)
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
