"""Dagster's webserver with the data root's plots on the same origin, at ``/quadcore-plots/``.

    python -m pipeline.run.webserver -w workspace.yaml -h 127.0.0.1 -p 3000   (what ``make ui`` starts)

The plots the assets write (``<data root>/plots/<content hash>.png``, see
:mod:`pipeline.plot_links`) are linked from their metadata as ``/quadcore-plots/<file>``: a path
without a host or port, which the browser resolves against the UI page itself. This process
serves that path from the data root it runs on (``QUADCORE_DATA_ROOT``, read when it starts), so
the plots show on any port, after a restart, and on a copied data root; nothing about where they
are served is stored in the event log. Everything else is Dagster's own webserver
(``dagster_webserver``), with its command-line options.
"""

from __future__ import annotations

import sys
from pathlib import Path

import dagster_webserver.cli as cli
from starlette.routing import Mount
from starlette.staticfiles import StaticFiles

from pipeline.plot_links import PLOTS_FOLDER, PLOTS_ROUTE
from pipeline.resources import data_root_from_env


def with_plots(app, folder: Path):
    """``app`` (Dagster's Starlette application) with ``folder`` served read-only under
    :data:`PLOTS_ROUTE`, ahead of Dagster's catch-all route."""
    folder.mkdir(parents=True, exist_ok=True)
    app.router.routes.insert(0, Mount(PLOTS_ROUTE, app=StaticFiles(directory=str(folder), check_dir=False),
                                      name="quadcore-plots"))
    return app


def main() -> None:
    folder = data_root_from_env().root_path / PLOTS_FOLDER
    create = cli.create_app_from_workspace_process_context
    cli.create_app_from_workspace_process_context = lambda *a, **k: with_plots(create(*a, **k), folder)
    sys.argv[0] = "dagster-webserver"
    cli.main()


if __name__ == "__main__":
    main()
