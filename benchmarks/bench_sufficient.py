"""Combining per-flight sufficient statistics (:mod:`quadcore.identify.stats.sufficient`): the cost of a fleet
fit and of a held-out test from statistics, at 19, 100 and 1,000 flights, for short and ten
times longer flights.

    python benchmarks/bench_sufficient.py

Synthetic statistics (random Gram matrices of every linear effect of the library, 1 s blocks):
the combine reads no rows, so its time must grow with the number of flights, not with their
samples. Figures: best of 3; "per flight" is the combine's time divided by the flights; the
ratio is the long flights' time over the short ones' (near 1 for the fit: it sums one matrix
per flight; the held-out test sums one per second of flight, still not one per sample).
"read": loading every flight's statistics from the data root (one file each; the per-block
matrices are read only when a held-out test asks for them); "held-out test": every flight held
out, its blocks read and scored.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from _common import best_of

from quadcore import effects
from quadcore.identify import evidence, fit as fitlib
from quadcore.identify.fit import solve
from quadcore.identify.stats import sufficient
from quadcore.physics import vehicle

VEHICLE = vehicle.load()
SAMPLE_HZ = 500


def synthetic(flight: str, seconds: int, layout: sufficient.Layout, rng: np.random.Generator) -> sufficient.FlightStats:
    """Statistics of a flight of ``seconds`` (one block a second, ``SAMPLE_HZ`` samples each)."""
    w = layout.width
    z = rng.standard_normal((seconds, 6, 16, w))  # 16 random rows per block: a Gram of full rank
    gram = np.einsum("bcni,bcnj->bcij", z, z) * (SAMPLE_HZ / 16)
    return sufficient.from_blocks(flight, layout, "synthetic", gram, np.full(seconds, SAMPLE_HZ),
                                  gram.sum(axis=0) / 4, np.full(6, 1e-3), 0.02, 3.9)


def fleet_fit(stats: list[sufficient.FlightStats]) -> solve.Fit:
    es = [effects.get("rotor_drag"), effects.get("thrust_scale")]
    return fitlib.fit_effects(es, stats, [s.layout.target() for s in stats], VEHICLE)


def held_out(stats: list[sufficient.FlightStats], fit: solve.Fit) -> evidence.HeldOutTest:
    e = effects.get("rotor_drag")
    resid = {s.flight: s.layout.target() for s in stats}
    pred = {s.flight: fit.predict([e], s, VEHICLE) for s in stats}
    return evidence.held_out_test(stats, resid, pred, evidence.channel_mask(["force"]))


def main() -> None:
    layout = sufficient.layout_of(e for e in effects.registry().values() if e.linear)  # no profiles: linear fits
    rng = np.random.default_rng(0)
    print(f"columns: {layout.width} (every linear coordinate of the library and y0); {SAMPLE_HZ} samples/s")
    print(f"{'flights':>8} {'s/flight':>9} {'samples':>12} {'read':>10} {'fit':>10} {'per flight':>11} "
          f"{'held-out test':>14} {'MB on disk':>11}")
    for n in (19, 100, 1000):
        times = {}
        for seconds in (10, 100):
            with tempfile.TemporaryDirectory(prefix="bench_sufficient_") as root:
                for i in range(n):
                    sufficient.save(synthetic(f"f{i:04d}", seconds, layout, rng), root)
                size = sum(p.stat().st_size for p in Path(root).rglob("*.bin")) / 1e6
                ids = [f"f{i:04d}" for i in range(n)]
                t_read, stats = best_of(lambda root=root, ids=ids: [sufficient.load(root, f) for f in ids])
                t_fit, fit = best_of(lambda stats=stats: fleet_fit(stats))
                # every flight held out: its blocks read from the file when first asked for
                t_test, _ = best_of(lambda root=root, ids=ids, fit=fit: held_out(
                    [sufficient.load(root, f) for f in ids], fit))
            times[seconds] = t_fit
            print(f"{n:8d} {seconds:9d} {n * seconds * SAMPLE_HZ:12,d} {t_read * 1e3:7.1f} ms {t_fit * 1e3:7.1f} ms "
                  f"{t_fit / n * 1e6:8.1f} us {t_test * 1e3:11.1f} ms {size:11.1f}")
        ratio = times[100] / times[10]
        print(f"{'':8} fit, 10x longer flights / short ones: ratio {ratio:.2f} (1: no growth with rows)")


if __name__ == "__main__":
    main()
