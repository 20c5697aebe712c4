"""What every command shares and ``quadcore --help`` may load: the user's error, a table printer, output
folders, progress on stderr. Standard library only (tests/test_import_graph.py checks that importing
:mod:`quadcore.cli` loads no numerical library)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path


class UserError(Exception):
    """A mistake in what the user asked for: printed as a message, exit code 2."""


def print_table(rows: list[list[str]], header: list[str]) -> None:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    for r in [header, ["-" * w for w in widths], *rows]:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)))


def output_folder(path: str) -> Path:
    """``path`` as an output folder: it must be a folder or not exist yet."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file, not a folder")
    return out


def output_folders(*paths: str | None) -> None:
    """Make the folders the outputs go to now, so that one that cannot be made (a file in the
    way, no permission) stops the command before the work, not after it (``OSError``: one line)."""
    for path in paths:
        if path:
            Path(path).mkdir(parents=True, exist_ok=True)


def warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def progress(args: argparse.Namespace) -> Callable[[str], None]:
    """Progress lines on stderr, none with ``--quiet``."""
    return (lambda m: print(m, file=sys.stderr)) if not args.quiet else (lambda m: None)
