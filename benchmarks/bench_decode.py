"""Decode speed on the real Crazyflie logs: quadcore against a plain ``struct`` loop.

    python benchmarks/bench_decode.py [LOGS_FOLDER]

LOGS_FOLDER defaults to ``<repo>/../shared/crazyflie/logs`` (the shared data set that sits
beside the clone). Every log file in it is decoded

- by quadcore, best of 3 each: ``quadcore.logs.logformat.decode_file`` (the vectorised decode
  alone: raw values, like the baseline), ``quadcore.logs.flight.decode_flight`` (decode + SI
  tables + provenance), and ``decode_flight`` + ``quadcore.physics.decoded_store.write_decoded`` (SI
  Parquet to a temp dir);
- by the baseline below: one ``struct.unpack_from`` per record, the obvious way to read the
  format (decode only, no SI, no Parquet), one pass.

Targets: the whole set decoded and written in under 0.5 s, and quadcore's decode at least
30x faster than the baseline (like for like: ``decode_file`` against the loop; the ratio
for ``decode_flight`` is printed too). This is a report, not a test: it exits 0 whether or not the
targets are met (and when the logs are absent).
"""

from __future__ import annotations

import struct
import sys
import tempfile
import zlib
from pathlib import Path

from _common import best_of

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a clone without installing

DEFAULT_LOGS = REPO.parent / "shared" / "crazyflie" / "logs"
TARGET_TOTAL_S = 0.5
TARGET_RATIO = 30.0
REPEATS = 3
MAIN_EVENT = "fixedFrequency"


# --------------------------------------------------------------------------------------
# Baseline: the format as described in quadcore/logs/logformat.py, read one record at a time.
# --------------------------------------------------------------------------------------

def _cstring(buf: bytes, pos: int) -> tuple[str, int]:
    end = buf.index(b"\x00", pos)
    return buf[pos:end].decode("ascii"), end + 1


def baseline_decode(buf: bytes) -> dict:
    """Decode a uSD log with a per-record ``struct.unpack_from`` loop.

    Returns ``{"version", "crc_ok", "tables": {event: {"timestamp": [...], var: [...]}}}``
    with raw (firmware-unit) values; timestamps in the file's native unit.
    """
    if not buf or buf[0] != 0xBC:
        raise ValueError("not a Crazyflie uSD log")
    version, n_types = struct.unpack_from("<HH", buf, 1)
    ts_char = {1: "I", 2: "Q"}[version]
    pos = 5
    events = {}  # id -> (name, variables, record struct)
    for _ in range(n_types):
        (eid,) = struct.unpack_from("<H", buf, pos)
        name, pos = _cstring(buf, pos + 2)
        (n_vars,) = struct.unpack_from("<H", buf, pos)
        pos += 2
        names, chars = [], []
        for _ in range(n_vars):
            spec, pos = _cstring(buf, pos)
            var, t = spec[:-1].split("(", 1)
            names.append(var)
            chars.append(t)
        events[eid] = (name, names, "<H" + ts_char + "".join(chars))

    end = len(buf) - 4
    crc_ok = (zlib.crc32(buf[:end]) & 0xFFFFFFFF) == struct.unpack_from("<I", buf, end)[0]
    rows: dict[int, list] = {eid: [] for eid in events}
    sizes = {eid: struct.calcsize(fmt) for eid, (_, _, fmt) in events.items()}
    while pos < end:
        (eid,) = struct.unpack_from("<H", buf, pos)
        if eid not in events:
            break  # chain broken
        size = sizes[eid]
        if pos + size > end:
            break  # partial record
        rows[eid].append(struct.unpack_from(events[eid][2], buf, pos))
        pos += size

    tables = {}
    for eid, (name, names, _) in events.items():
        cols = list(zip(*rows[eid])) if rows[eid] else [()] * (len(names) + 2)
        tables[name] = {"timestamp": list(cols[1]), **{v: list(c) for v, c in zip(names, cols[2:])}}
    return {"version": version, "crc_ok": crc_ok, "tables": tables}


# --------------------------------------------------------------------------------------

def find_logs(folder: Path) -> list[Path]:
    from quadcore.logs import flight

    return flight.discover_logs(folder)


def main(argv: list[str]) -> int:
    folder = Path(argv[0]) if argv else DEFAULT_LOGS
    if not folder.is_dir():
        print(f"bench_decode: logs folder not found: {folder}")
        print("The shared Crazyflie data set is absent on this machine; pass its path as the first argument.")
        return 0

    from quadcore.logs import flight, logformat
    from quadcore.physics import decoded_store

    paths = find_logs(folder)
    if not paths:
        print(f"bench_decode: no log files in {folder}")
        return 0
    total_bytes = sum(p.stat().st_size for p in paths)
    mb = total_bytes / 1e6

    def quadcore_raw():
        return [logformat.decode_file(p) for p in paths]

    def quadcore_decode():
        return [flight.decode_flight(p) for p in paths]

    def quadcore_decode_write():
        with tempfile.TemporaryDirectory(prefix="quadcore-bench-") as tmp:
            fls = []
            for p in paths:
                fl = flight.decode_flight(p)
                decoded_store.write_decoded(Path(tmp), fl)
                fls.append(fl)
            return fls

    quadcore_decode()  # warm-up: imports, numpy/polars/pyarrow first-call costs
    t_raw, _ = best_of(quadcore_raw)
    t_dec, flights = best_of(quadcore_decode)
    t_all, _ = best_of(quadcore_decode_write)
    rows = sum(f.provenance.rows.get(MAIN_EVENT, 0) for f in flights)
    failed = [f.flight_id for f in flights if f.warnings]

    def baseline():
        return [baseline_decode(p.read_bytes()) for p in paths]

    t_base, base = best_of(baseline, repeats=1)
    base_rows = sum(len(b["tables"].get(MAIN_EVENT, {}).get("timestamp", [])) for b in base)

    ratio = t_base / t_raw if t_raw > 0 else float("inf")
    ratio_si = t_base / t_dec if t_dec > 0 else float("inf")
    print(f"Logs:            {folder}")
    print(f"Files:           {len(paths)}")
    print(f"Total size:      {mb:.2f} MB")
    print(f"{MAIN_EVENT} rows: {rows:,} (baseline: {base_rows:,})")
    if failed:
        print(f"Decode warnings in: {', '.join(failed)}")
    print()
    W = 38
    print(f"{'':{W}}{'seconds':>9}  {'MB/s':>8}")
    print(f"{'quadcore decode only, raw':{W}}{t_raw:9.3f}  {mb / t_raw:8.1f}")
    print(f"{'quadcore decode + SI (decode_flight)':{W}}{t_dec:9.3f}  {mb / t_dec:8.1f}")
    print(f"{'quadcore decode + SI + Parquet':{W}}{t_all:9.3f}  {mb / t_all:8.1f}")
    print(f"{'baseline struct loop (1 pass)':{W}}{t_base:9.3f}  {mb / t_base:8.1f}")
    print("(quadcore figures: best of 3)")
    print(f"\nSpeed ratio, baseline / quadcore raw decode:   {ratio:.1f}x")
    print(f"Speed ratio, baseline / quadcore decode + SI:  {ratio_si:.1f}x")
    print()
    ok_total = t_all < TARGET_TOTAL_S
    ok_ratio = ratio >= TARGET_RATIO
    print(f"Target: whole set decoded + written < {TARGET_TOTAL_S} s: "
          f"{'MET' if ok_total else 'NOT MET'} ({t_all:.3f} s)")
    print(f"Target: decode >= {TARGET_RATIO:.0f}x faster than the struct loop: "
          f"{'MET' if ok_ratio else 'NOT MET'} ({ratio:.1f}x raw decode, {ratio_si:.1f}x with SI)")
    if rows != base_rows:
        print(f"NOTE: quadcore and the baseline disagree on {MAIN_EVENT} rows ({rows} vs {base_rows})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
