"""The fuzz harness: decode mutants of good logs, write what they hold under a data root, and
count what the issue's bar asks for.

    python -m tests.fuzz.harness [--mutants 2000] [--structure 200] [--kills 100] [--logs DIR]     (make fuzz)

Good logs: the real Crazyflie logs (``../shared/crazyflie/logs``, the three smallest), or
simulated ones where they are absent. For every mutant: the decoder either returns or raises
a ``LogFormatError`` (anything else is an untyped exception), within ``MAX_SECONDS``; what it
returns is written with :func:`quadcore.physics.decoded_store.write_decoded` under one data root, and no file may
appear outside it; every whole record before the corrupted bytes is kept; after a corruption
in the body, the share of the records after it that is recovered is measured (median >= 90 %).
Then the structure-aware cases of :mod:`.structure` (field-boundary cuts, edited headers, hostile
names, timestamp jumps, records with another valid id, late corruptions, joined logs): 0
tracebacks, 0 hangs, 0 phantom records, 0 intact records lost where the bytes allow recovery.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadcore.logs import flight, logformat
from quadcore.physics import decoded_store

from . import structure
from .mutants import ESCAPE_MARK, Layout, Mutant, layout, mutants

MAX_SECONDS = 2.0
BODY_KINDS = ("flip", "overwrite", "insert", "delete", "unknown_id")
REAL_LOGS = Path(__file__).resolve().parents[3] / "shared" / "crazyflie" / "logs"


@dataclass(frozen=True)
class Outcome:
    kind: str
    seconds: float
    typed_error: str | None = None
    untyped_error: str | None = None
    prefix_kept: bool | None = None  # None: no corrupted range to check against
    recovered: float | None = None  # share of the records after a body corruption that came back
    phantoms: int | None = None  # records not in the log beyond the damaged ones (None: not judged)


@dataclass(frozen=True)
class Clean:
    """A good log, decoded, with its record layout."""

    data: bytes
    log: logformat.DecodedLog
    lay: Layout
    ids: np.ndarray  # event id of each record, in file order
    src: structure.Source  # its records' bytes, to judge phantoms (tests/fuzz/structure.py)

    @classmethod
    def of(cls, data: bytes) -> Clean:
        lay = layout(data)
        ids = np.array([int.from_bytes(data[s:s + 2], "little") for s in lay.record_starts])
        return cls(data, logformat.decode_bytes(data), lay, ids, structure.Source.of(data))


# Mutants whose records' bytes are the log's own, except in the corrupted range: a decoded record
# that is none of the log's records, beyond those the range overlaps, is a phantom.
PHANTOM_KINDS = (*BODY_KINDS, "truncate", "hostile_event_name")


def _phantoms(m: Mutant, clean: Clean, log: logformat.DecodedLog) -> int:
    starts, sizes = clean.lay.record_starts, clean.lay.record_sizes
    damaged: dict[int, int] = {}
    if m.corrupt_from is not None and m.corrupt_to is not None:
        a, b = m.corrupt_from, (m.corrupt_from + 1 if m.kind == "insert" else m.corrupt_to)
        hit = clean.ids[(starts < b) & (starts + sizes > a)]
        damaged = {int(e): int(np.count_nonzero(hit == e)) for e in np.unique(hit)}
    every = clean.src.keys(range(len(clean.ids)))
    return structure.judge(structure.Case(m.kind, m.data, {}, every, damaged, check_lost=False), log).phantoms


def _prefix_kept(log: logformat.DecodedLog, clean: Clean, before: int) -> bool:
    """Every clean record ending at or before byte ``before`` is in ``log``, unchanged."""
    ends = clean.lay.record_starts + clean.lay.record_sizes
    whole = ends <= before
    for name, et in clean.log.event_types.items():
        n = int(np.count_nonzero(whole & (clean.ids == et.event_id)))
        if n == 0:
            continue
        got = next((k for k, e in log.event_types.items() if e.event_id == et.event_id), None)
        if got is None or len(log.tables[got]) < n:
            return False
        if not np.array_equal(log.timestamps_us[got][:n], clean.log.timestamps_us[name][:n]):
            return False
        if log.tables[got][:n].tobytes() != clean.log.tables[name][:n].tobytes():
            return False
    return True


def _recovered(log: logformat.DecodedLog, clean: Clean, corrupt_from: int) -> float:
    """Records decoded after the corruption over the clean records after it (capped at 1)."""
    ends = clean.lay.record_starts + clean.lay.record_sizes
    before = int(np.count_nonzero(ends <= corrupt_from))
    after_clean = len(clean.ids) - before
    if after_clean <= 0:
        return 1.0
    return min(1.0, max(0, sum(log.rows().values()) - before) / after_clean)


def check(m: Mutant, clean: Clean, root: Path, flight_id: str) -> Outcome:
    t0 = time.perf_counter()
    try:
        log = logformat.decode_bytes(m.data)
    except logformat.LogFormatError as exc:
        return Outcome(m.kind, time.perf_counter() - t0, typed_error=type(exc).__name__)
    except Exception as exc:  # noqa: BLE001 (what the harness counts)
        return Outcome(m.kind, time.perf_counter() - t0, untyped_error=_short(exc))
    seconds = time.perf_counter() - t0
    try:
        decoded_store.write_decoded(root, flight.from_decoded(flight_id, log, f"mutant:{m.kind}"))
    except Exception as exc:  # noqa: BLE001
        return Outcome(m.kind, seconds, untyped_error=f"writing: {_short(exc)}")
    cut = len(m.data) if m.kind == "truncate" else m.corrupt_from
    kept = _prefix_kept(log, clean, cut) if cut is not None else None
    recovered = _recovered(log, clean, m.corrupt_from) if m.kind in BODY_KINDS and m.corrupt_from is not None else None
    phantoms = _phantoms(m, clean, log) if m.kind in PHANTOM_KINDS else None
    return Outcome(m.kind, seconds, prefix_kept=kept, recovered=recovered, phantoms=phantoms)


def _short(exc: Exception) -> str:
    where = traceback.extract_tb(exc.__traceback__)[-1]
    return f"{type(exc).__name__}: {str(exc)[:120]} ({Path(where.filename).name}:{where.lineno})"


def _files_outside(sandbox: Path, root: Path) -> list[Path]:
    outside = [p for p in sandbox.rglob("*") if p.is_file() and root not in p.parents]
    return outside + [p for p in Path(tempfile.gettempdir()).glob(f"*{ESCAPE_MARK}*")]


@dataclass(frozen=True)
class Summary:
    mutants: int
    by_kind: dict[str, int]
    typed_errors: int
    untyped_errors: list[str]
    max_seconds: float
    over_time: int
    files_outside_root: int
    prefix_checked: int
    prefix_lost: int
    body_corruptions: int
    recovered_median: float
    recovered_p10: float
    phantom_checked: int = 0
    phantoms: int = 0

    def ok(self) -> bool:
        return (not self.untyped_errors and self.over_time == 0 and self.files_outside_root == 0
                and self.prefix_lost == 0 and self.recovered_median >= 0.9 and self.phantoms == 0)

    def lines(self) -> list[str]:
        return [
            f"mutants decoded: {self.mutants} ({', '.join(f'{k} {n}' for k, n in sorted(self.by_kind.items()))})",
            f"refused with a typed LogFormatError: {self.typed_errors}",
            f"untyped exceptions: {len(self.untyped_errors)}",
            f"slowest decode: {self.max_seconds * 1e3:.0f} ms (over {MAX_SECONDS:g} s: {self.over_time})",
            f"files written outside the data root: {self.files_outside_root}",
            f"whole records before the first corruption lost: {self.prefix_lost} of {self.prefix_checked} mutants",
            f"records after a body corruption recovered: median {self.recovered_median:.1%}, "
            f"10th percentile {self.recovered_p10:.1%} ({self.body_corruptions} mutants)",
            f"phantom records (not in the log, beyond the damaged ones): {self.phantoms} "
            f"({self.phantom_checked} mutants judged)",
        ]


def run(logs: list[bytes], n: int, sandbox: Path, seed: int = 0, log=print) -> Summary:
    root = sandbox / "root"
    outcomes: list[Outcome] = []
    per_log = -(-n // len(logs))
    for j, data in enumerate(logs):
        clean = Clean.of(data)
        for i, m in enumerate(mutants(data, min(per_log, n - len(outcomes)), seed=seed + j)):
            outcomes.append(check(m, clean, root, f"log{j}-m{i:05d}"))
            if len(outcomes) % 500 == 0:
                log(f"  {len(outcomes)} mutants")
    rec = np.array([o.recovered for o in outcomes if o.recovered is not None])
    kinds: dict[str, int] = {}
    for o in outcomes:
        kinds[o.kind] = kinds.get(o.kind, 0) + 1
    return Summary(
        mutants=len(outcomes),
        by_kind=kinds,
        typed_errors=sum(o.typed_error is not None for o in outcomes),
        untyped_errors=[f"{o.kind}: {o.untyped_error}" for o in outcomes if o.untyped_error],
        max_seconds=max(o.seconds for o in outcomes),
        over_time=sum(o.seconds > MAX_SECONDS for o in outcomes),
        files_outside_root=len(_files_outside(sandbox, root)),
        prefix_checked=sum(o.prefix_kept is not None for o in outcomes),
        prefix_lost=sum(o.prefix_kept is False for o in outcomes),
        body_corruptions=len(rec),
        recovered_median=float(np.median(rec)) if len(rec) else 1.0,
        recovered_p10=float(np.percentile(rec, 10)) if len(rec) else 1.0,
        phantom_checked=sum(o.phantoms is not None for o in outcomes),
        phantoms=sum(o.phantoms or 0 for o in outcomes),
    )


def good_logs(folder: Path | None, count: int = 3) -> tuple[list[bytes], str]:
    """The ``count`` smallest logs of ``folder`` (default: the real logs), or simulated ones."""
    folder = folder or REAL_LOGS
    if folder.is_dir():
        paths = sorted(flight.discover_logs(folder), key=lambda p: p.stat().st_size)[:count]
        return [p.read_bytes() for p in paths], f"real logs {', '.join(p.name for p in paths)} from {folder}"
    from quadcore.sim import simulation

    with tempfile.TemporaryDirectory() as tmp:
        configs = [simulation.SimConfig(kind="random", duration_s=10.0, seed=s) for s in range(count)]
        written = simulation.simulate_set(Path(tmp), configs, {})
        return [p.read_bytes() for p, _ in written], f"{count} simulated logs ({folder} is absent)"


def _pipeline_kills(n: int, seed: int) -> bool:
    from quadcore.sim import simulation

    from . import kills

    print(f"\nkilling `python -m pipeline` {n} times at random moments (4 simulated flights)")
    with tempfile.TemporaryDirectory(prefix="quadcore-pipeline-kills-") as tmp:
        raw = Path(tmp) / "raw"
        simulation.simulate_set(raw, [simulation.SimConfig(kind="random", duration_s=5.0, seed=s)
                                      for s in range(1, 5)], {})
        report = kills.run_pipeline(Path(tmp) / "root", raw, n, seed)
    print(f"pipeline kills: {report.kills}; torn files: {report.torn_files}; unloadable learned models: "
          f"{report.unloadable_models}; the run after them exited {report.final_exit_code} and left "
          f"{report.leftovers_after_final_run} temp files")
    return report.torn_files == report.unloadable_models == report.final_exit_code == \
        report.leftovers_after_final_run == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mutants", type=int, default=2000)
    parser.add_argument("--kills", type=int, default=100)
    parser.add_argument("--pipeline-kills", type=int, default=0,
                        help="also kill `python -m pipeline` this many times on 4 simulated flights")
    parser.add_argument("--structure", type=int, default=200,
                        help="structure-aware cases per drawn family and log (tests/fuzz/structure.py; 0: none)")
    parser.add_argument("--logs", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logs, what = good_logs(args.logs)
    print(f"fuzzing {args.mutants} mutants of {what}")
    t0 = time.perf_counter()
    ok = True
    if args.mutants:
        with tempfile.TemporaryDirectory(prefix="quadcore-fuzz-") as tmp:
            summary = run(logs, args.mutants, Path(tmp), args.seed)
        print("\n".join(summary.lines()) + f"\n({time.perf_counter() - t0:.0f} s)")
        for e in summary.untyped_errors[:10]:
            print(f"  untyped: {e}")
        ok = summary.ok()
    if args.structure:
        print(f"\nstructure-aware cases of {what}")
        t1 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="quadcore-fuzz-structure-") as tmp:
            tally = structure.run(logs, args.structure, args.seed, write_root=Path(tmp) / "root")
            outside = _files_outside(Path(tmp), Path(tmp) / "root")
        print("\n".join(tally.lines()) + f"\nfiles written outside the data root: {len(outside)}"
              f"\n({time.perf_counter() - t1:.0f} s)")
        for e in tally.tracebacks[:10]:
            print(f"  traceback: {e}")
        ok = ok and tally.ok() and not outside
    if args.kills:
        from . import kills

        print(f"\nkilling writers {args.kills} times at random moments")
        with tempfile.TemporaryDirectory(prefix="quadcore-kills-") as tmp:
            report = kills.run(Path(tmp), args.kills, args.seed)
        print(f"kills: {report.kills}; torn files: {report.torn_files}; unloadable learned models: "
              f"{report.unloadable_models}; leftovers swept: {report.leftovers_before_sweep}, "
              f"left after the sweep: {report.leftovers_after_sweep}")
        ok = ok and report.torn_files == report.unloadable_models == report.leftovers_after_sweep == 0
    if args.pipeline_kills:
        ok = _pipeline_kills(args.pipeline_kills, args.seed) and ok
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
