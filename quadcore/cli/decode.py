"""``quadcore decode``: uSD logs -> SI Parquet under a data root."""

from __future__ import annotations

import argparse

from quadcore.cli.base import output_folder, print_table
from quadcore.cli.common import load_flights


def cmd_decode(args: argparse.Namespace) -> int:
    out = output_folder(args.out)
    flights, quarantined = load_flights(args.paths, out)
    events = sorted({e for f in flights for e in f.tables})
    rows = [[f.flight_id, *[str(f.provenance.rows.get(e, 0)) for e in events], str(len(f.warnings))]
            for f in flights]
    totals = ["TOTAL", *[str(sum(f.provenance.rows.get(e, 0) for f in flights)) for e in events],
              str(sum(len(f.warnings) for f in flights))]
    print()
    print_table(rows + [totals], ["flight", *events, "warnings"])
    print(f"\n{len(flights)} flights decoded to {out.resolve() / 'decoded'}")
    for e in events:
        print(f"  {e}: {out.resolve() / 'decoded' / e}/flight=*/data.parquet")
    if quarantined:
        print(f"{len(quarantined)} file(s) quarantined (see {out.resolve() / 'quarantine'}):")
        for fid, reason in quarantined.items():
            print(f"  {fid}: {reason}")
    return 0 if flights else 1
