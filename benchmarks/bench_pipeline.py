"""The main job as a user runs it, on the real logs and on the demo.

    python benchmarks/bench_pipeline.py [LOGS_FOLDER]

- the 19 real logs on an empty data root (``QUADCORE_RAW_DIR=LOGS python -m pipeline``): <= 60 s;
- one new log added to them (a copy of jana02 under a new name, in a folder of links to the
  others): the next run decodes and recomputes that flight only and refreshes the fitted model,
  the diagnosis and the history: <= 10 s (figure: the whole job; the refresh alone is printed too);
- the same run again with nothing new: nothing is redone;
- the demo (no logs: six simulated flights, the loop's second turn): <= 30 s.

Wall time of a fresh ``python -m pipeline`` process each (imports included), with the seconds of
its stages beside (1 decode, 2 fit + diagnosis, 3 residuals/rollouts/MCAP, 4 learning). The ratio
is target / figure (above 1: the target is met). A report, not a test: exits 0 either way.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from _common import logs_folder
from _jobs import report, run_main_job


def _stages(run) -> str:
    return "  stages: " + ", ".join(f"{k}: {v:.1f} s" for k, v in sorted(run.stage_s.items()))


def main() -> None:
    logs = logs_folder()
    with tempfile.TemporaryDirectory(prefix="bench_pipeline_") as folder:
        tmp = Path(folder)
        raw = tmp / "raw"
        raw.mkdir()
        for log in sorted(p for p in logs.iterdir() if p.is_file()):
            (raw / log.name).symlink_to(log)
        first = run_main_job(tmp / "real", raw)
        report(f"main job, {len(list(raw.iterdir()))} real logs, empty data root", first.wall_s, 60.0)
        print(_stages(first), f" peak memory {first.peak_rss_mb:.0f} MB", "" if first.returncode == 0 else "FAILED")

        shutil.copyfile(logs / "jana02", raw / "jana99")
        new = run_main_job(tmp / "real", raw)
        report("main job, one new log added", new.wall_s, 10.0)
        print(_stages(new), "  (decode + refit + diagnosis + history: stages 1-3)")

        again = run_main_job(tmp / "real", raw)
        report("main job, nothing new", again.wall_s, 10.0)

        demo_dir = tmp / "demo"
        demo_dir.mkdir()
        demo = run_main_job(demo_dir / "data", None, cwd=demo_dir)
        report("demo main job (6 simulated flights, two turns of the loop)", demo.wall_s, 30.0)
        print(_stages(demo))


if __name__ == "__main__":
    main()
