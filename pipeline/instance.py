"""The persistent Dagster instance that ``make run`` and ``make ui`` share."""

import os
from pathlib import Path

# Two cores: at most two runs at once; the others wait in the queue (``dg dev`` and the daemon
# use the queued run coordinator). SQLite storage also locks under more concurrent writers.
DAGSTER_YAML = """\
# Written by quadcore (`make run` / `make ui`). Two cores: at most two runs at once, the rest queue.
concurrency:
  runs:
    max_concurrent_runs: 2
telemetry:
  enabled: false
"""


def ensure_dagster_home(root: Path) -> Path:
    """Use ``$DAGSTER_HOME`` or ``<root>/.dagster``; create it with our dagster.yaml if it has none."""
    home = Path(os.environ.get("DAGSTER_HOME") or root / ".dagster").resolve()
    home.mkdir(parents=True, exist_ok=True)
    if not (home / "dagster.yaml").exists():
        (home / "dagster.yaml").write_text(DAGSTER_YAML)
    os.environ["DAGSTER_HOME"] = str(home)
    return home
