"""``python -m pipeline``: the main job (:mod:`pipeline.run.main`).

Python's cyclic garbage collector is kept out of the way of what a batch job does not need:
it is paused while Dagster, SciPy, polars and matplotlib are imported (they make millions of
long-lived objects, and each full collection walks them all), those objects are then frozen
(later collections skip them), full collections run a tenth as often (torch and XGBoost,
imported by the learning stage, and each run's objects would otherwise be walked again every
70,000 allocations), and everything left is frozen again before the interpreter tears itself
down (its last full collection walks the whole heap once more). Measured here: importing
pipeline.run.main 1.95 -> 1.52 s CPU, exiting after it 2.2 -> 0.2 s; in the demo job, 14 full
collections (4.3 s) -> 1 (0.9 s). Memory is still freed by reference counting as before; only
garbage in reference cycles waits longer."""

import gc
import sys

# A full collection after this many collections of the middle generation (Python's default: 10).
FULL_COLLECTION_EVERY = 100

gc.disable()
try:
    from pipeline.resources import SettingError

    try:
        from pipeline.run.main import main
    except SettingError as exc:  # a bad QUADCORE_* setting read with the definitions: one line, exit 2
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
finally:
    gc.enable()
gc.freeze()
young, middle, _ = gc.get_threshold()
gc.set_threshold(young, middle, FULL_COLLECTION_EVERY)

code = main(sys.argv[1:])
gc.freeze()
sys.exit(code)
