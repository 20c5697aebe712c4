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

The package: :mod:`quadcore.cli.parser` builds every verb's parser; each command group is a module of its
own that imports what its commands need at module level (``decode``; ``physics``: vehicle, residuals,
fit-thrust; ``sim``: simulate; ``export``: export, export-c; ``diagnose``; ``discover``; ``plan``;
``learn``: train), beside ``base`` (standard library only) and ``common`` (what several groups share).
:func:`_load` is the one place a group is imported: by name, when its command runs, so that
``quadcore --help`` starts without numpy, polars, scipy, torch, XGBoost or Dagster
(docs/benchmarks.md, "Start-up of the CLI").
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import sys
from collections.abc import Iterator
from types import ModuleType

from quadcore.cli.base import UserError, output_folder
from quadcore.cli.parser import build_parser
from quadcore.store import ownership, safewrite

__all__ = ["UserError", "build_parser", "main"]


def _load(name: str) -> ModuleType:
    """The module ``quadcore.cli.<name>`` (a command group, or ``common``), imported now: the CLI's one
    lazy-load point (tests/test_import_graph.py allow-lists it; each group imports its stage at module level)."""
    return importlib.import_module(f"quadcore.cli.{name}")


# Verbs that write a data root (``--out``): they hold its lock, so that two jobs on one root wait
# for each other instead of interleaving, and sweep what killed runs left there.
DATA_ROOT_VERBS = ("decode", "train")


@contextlib.contextmanager
def _data_root_held(args: argparse.Namespace) -> Iterator[None]:
    if args.verb not in DATA_ROOT_VERBS:
        yield
        return
    out = output_folder(args.out)
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
            return getattr(_load(args.group), args.command)(args)
    except OSError as exc:  # a folder that cannot be written, a file where a folder should be, ...
        print(f"quadcore {args.verb}: error: {exc.strerror or exc}: {exc.filename or ''}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # commands return their code: this came from user code (a plugin)
        print(f"quadcore {args.verb}: error: code run by the command (an effect plugin?) called "
              f"exit({exc.code!r}); the command did not finish", file=sys.stderr)
        return 2
    except Exception as exc:
        if not isinstance(exc, _load("common").USER_ERRORS):
            raise
        print(f"quadcore {args.verb}: error: {exc}", file=sys.stderr)
        return 2
