"""``quadcore plan``: the next flight, a trajectory that separates what the data cannot tell apart."""

from __future__ import annotations

import argparse
from pathlib import Path

from quadcore.cli.base import UserError, output_folders, progress
from quadcore.cli.common import model_and_flights
from quadcore.plan import limits, planner, question
from quadcore.workflows import identify, plan as planflow


def cmd_plan(args: argparse.Namespace) -> int:
    """The flight that separates what the diagnosis cannot tell apart (``docs/flight-planning.md``)."""
    request = _plan_request(args)
    output_folders(str(Path(args.json).parent), str(Path(args.trajectory).parent))
    spec, flights, holdout = model_and_flights(args)
    diag = identify.diagnose(flights, spec, holdout, progress(args), where=args.data)
    try:
        result = planflow.plan(flights, spec, diag, request, progress(args))
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
    if result.measured_before is not None:
        print(f"  measured on the logged flights: separation {result.measured_before:.3g} σ, score gap "
              f"{result.gap_before:.3g}" + (f" ({result.undecided_before})" if result.undecided_before else ""))
    if result.design.get("note"):  # why the measured separation and the design's differ
        print(f"  note: {result.design['note']}")
    if result.design.get("expected_to_decide") is False:
        print("  note: the best flight of the family is not predicted to break the tie with margin "
              f"(objective {result.design['after']['value']:.2f} < 1): {result.design.get('advice', '')}; "
              "see docs/flight-planning.md")
    for f in result.proof:
        print(f"  flown with {f.truth} true: diagnosis ranks {f.top} first"
              + (f", tied with {', '.join(f.tied_with)}" if f.tied_with else ", no tie")
              + (f"; separation {f.sigma:.1f} σ" if f.sigma is not None else "")
              + (f" ({f.undecided})" if f.undecided else ""))
    for left in result.proof_left_out:
        print(f"  warning: not in the proof, the flight with {left.truth} true: {left.reason}")
    print(f"wrote {written.trajectory}, {written.plot} and {written.json}")
    return 0


def _plan_request(args: argparse.Namespace) -> planner.PlanRequest:
    """The plan's question, limits and flight time from the command line (``UserError`` if bad)."""
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
