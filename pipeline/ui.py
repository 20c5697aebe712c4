"""``make ui``: Dagster's UI and daemon (``dg dev``) on the persistent instance, for a lab to leave running.

    python -m pipeline.ui [--port 3000] [--host 127.0.0.1]

- ``$DAGSTER_HOME`` (default ``<data root>/.dagster``) gets a ``dagster.yaml`` with a run queue
  limited to two runs at once (the machine has two cores), if it has none yet.
- A port already in use is one line on stderr and exit code 2, before anything starts.
- The plots of the assets (``<data root>/plots``) are served on ``--plots-port`` (default: the
  next port), so that the asset pages show them without a click (see ``pipeline.plot_links``).
- ``dg dev`` runs in its own process group; SIGINT or SIGTERM to this process stops it and
  everything it started (webserver, daemon, code server), also when started without a
  terminal (where ``dg dev`` alone ignores both).
"""

from __future__ import annotations

import argparse
import errno
import functools
import http.server
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# How long the services get to stop after an interrupt before they are killed.
STOP_TIMEOUT_S = 20.0


def port_problem(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be served (in use, not allowed), or None if it can."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        # as the servers do: connections of a previous server closing (TIME_WAIT) do not count
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return f"port {port} on {host} is already in use; choose another with PORT={port + 1} make ui"
            return f"cannot serve on {host}:{port}: {exc.strerror}"
    return None


def serve_plots(folder: Path, host: str, port: int) -> http.server.ThreadingHTTPServer:
    """Serve the PNGs of ``folder`` read-only on ``host:port`` in a background thread."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):  # the UI asks for every plot it shows: not worth a line each
            pass

    folder.mkdir(parents=True, exist_ok=True)
    server = http.server.ThreadingHTTPServer((host, port), functools.partial(Quiet, directory=str(folder)))
    threading.Thread(target=server.serve_forever, name="plots", daemon=True).start()
    return server


def dev_command(host: str, port: int) -> list[str]:
    """``dg dev`` (Dagster's current command; ``dagster dev`` is superseded by it) on our workspace."""
    dg = shutil.which("dg", path=str(Path(sys.executable).parent)) or shutil.which("dg")
    if dg is None:
        raise FileNotFoundError("the `dg` command (package dagster-dg-cli) is not installed; run `make install`")
    return [dg, "dev", "-w", str(REPO / "workspace.yaml"), "-h", host, "-p", str(port)]


def _restore_default_signals() -> None:
    # A process started in the background inherits SIGINT ignored, and Python then never turns
    # it into KeyboardInterrupt: give the services the default handling back.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def serve(cmd: list[str], env: dict[str, str]) -> int:
    """Run ``cmd`` in its own process group until it exits or we are told to stop."""
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, start_new_session=True, preexec_fn=_restore_default_signals)
    stopping = []

    def stop(signum, _frame):
        stopping.append(signum)
        try:
            os.kill(proc.pid, signal.SIGINT)  # dg dev shuts its services down on an interrupt
        except ProcessLookupError:
            pass

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    while True:
        try:
            code = proc.wait(timeout=1.0 if not stopping else STOP_TIMEOUT_S)
            break
        except subprocess.TimeoutExpired:
            if stopping:
                print(f"make ui: services did not stop within {STOP_TIMEOUT_S:.0f} s; killing them", file=sys.stderr)
                os.killpg(proc.pid, signal.SIGKILL)
                code = proc.wait()
                break
    _end_group(proc.pid)
    return 0 if stopping else code


def _end_group(pgid: int) -> None:
    """Whatever the services left behind in their process group (a code server) goes too."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.ui", description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=int(os.environ.get("PORT", "3000")))
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--plots-port", type=int, default=None, help="where the plots are served (default: port + 1)")
    args = parser.parse_args(argv)
    plots_port = args.plots_port or args.port + 1
    for port in (args.port, plots_port):
        problem = port_problem(args.host, port)
        if problem:
            print(f"make ui: error: {problem}", file=sys.stderr)
            return 2
    from pipeline.instance import ensure_dagster_home
    from pipeline.plot_links import PLOTS_FOLDER, PLOTS_URL_ENV
    from pipeline.resources import data_root_from_env
    from quadcore.store import store

    root = data_root_from_env().root_path
    home = ensure_dagster_home(root)
    # an object-store root keeps its plots inline (plot_links): nothing to serve from this disk
    plots = None if store.is_remote(root) else serve_plots(root / PLOTS_FOLDER, args.host, plots_port)
    try:
        cmd = dev_command(args.host, args.port)
    except FileNotFoundError as exc:
        print(f"make ui: error: {exc}", file=sys.stderr)
        return 2
    print(f"Dagster UI on http://{args.host}:{args.port} (instance {home}); Ctrl-C stops it", flush=True)
    try:
        return serve(cmd, {**os.environ, "DAGSTER_HOME": str(home),
                           **({PLOTS_URL_ENV: f"http://{args.host}:{plots_port}"} if plots else {})})
    finally:
        if plots is not None:
            plots.shutdown()


if __name__ == "__main__":
    sys.exit(main())
