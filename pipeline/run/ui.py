"""``make ui``: Dagster's UI and daemon on the persistent instance, for a lab to leave running.

    python -m pipeline.run.ui [--port 3000] [--host 127.0.0.1]

- ``$DAGSTER_HOME`` (default ``<data root>/.dagster``) gets a ``dagster.yaml`` with a run queue
  limited to two runs at once (the machine has two cores), if it has none yet.
- A port already in use is one line on stderr and exit code 2, before anything starts.
- The services ``dg dev`` would start, Dagster's webserver and daemon, with the webserver
  serving the data root's plots on its own origin (``/quadcore-plots/``, see
  :mod:`pipeline.run.webserver`), so that the asset pages show them on any port.
- The services run in a process group of their own; SIGINT or SIGTERM to this process stops them
  and everything they started (code servers), also when started without a terminal.
"""

from __future__ import annotations

import argparse
import errno
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from pipeline.resources import SettingError, choose_demo, data_root_from_env, make_command
from pipeline.run.instance import ensure_dagster_home
from quadcore.store import ownership

REPO = Path(__file__).resolve().parents[2]
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
                return f"port {port} on {host} is already in use; choose another: {make_command('ui', port + 1)}"
            return f"cannot serve on {host}:{port}: {exc.strerror}"
    return None


def service_commands(host: str, port: int) -> list[list[str]]:
    """The UI's two services on our workspace: Dagster's webserver with the data root's plots on
    the same origin (:mod:`pipeline.run.webserver`), and Dagster's daemon (sensors, schedules,
    automation, the run queue). What ``dg dev`` starts, with the webserver extended; each loads
    the code location from ``workspace.yaml`` itself."""
    daemon = shutil.which("dagster-daemon", path=str(Path(sys.executable).parent)) or shutil.which("dagster-daemon")
    if daemon is None:
        raise FileNotFoundError("the `dagster-daemon` command (package dagster) is not installed; run `make install`")
    workspace = str(REPO / "workspace.yaml")
    return [[sys.executable, "-m", "pipeline.run.webserver", "-w", workspace, "-h", host, "-p", str(port)],
            [daemon, "run", "-w", workspace]]


def _restore_default_signals() -> None:
    # A process started in the background inherits SIGINT ignored, and Python then never turns
    # it into KeyboardInterrupt: give the services the default handling back.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def answers(url: str) -> bool:
    """Whether the webserver at ``url`` answers (its ``/server_info``)."""
    try:
        with urllib.request.urlopen(f"{url}/server_info", timeout=1):
            return True
    except (OSError, ValueError):
        return False


def serve(cmds: list[list[str]], env: dict[str, str], url: str = "") -> int:
    """Run ``cmds`` in one process group of their own until one exits or we are told to stop;
    then interrupt them all (and kill what is left after :data:`STOP_TIMEOUT_S`). With ``url``,
    say once when the webserver there answers (it takes seconds, a minute on a loaded machine)."""
    # a process group of their own (in this session: a group of another session cannot be joined),
    # so that a terminal's Ctrl-C reaches this process only, which stops them in order
    first = subprocess.Popen(cmds[0], cwd=REPO, env=env, process_group=0, preexec_fn=_restore_default_signals)
    procs = [first] + [subprocess.Popen(cmd, cwd=REPO, env=env, process_group=first.pid,
                                        preexec_fn=_restore_default_signals) for cmd in cmds[1:]]
    stopping: list[int] = []

    def stop(signum, _frame):
        stopping.append(signum)

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    code, started = None, time.time()
    while not stopping and code is None:
        time.sleep(0.5)
        code = next((p.returncode for p in procs if p.poll() is not None), None)
        if url and code is None and answers(url):
            print(f"make ui: ready after {time.time() - started:.0f} s: open {url}", flush=True)
            url = ""
    if code is not None and not stopping:
        print(f"make ui: a service stopped (exit code {code}); stopping the others", file=sys.stderr)
    try:
        os.killpg(first.pid, signal.SIGINT)  # the webserver and the daemon shut down on an interrupt
    except ProcessLookupError:
        pass
    deadline = time.time() + STOP_TIMEOUT_S
    for p in procs:
        try:
            p.wait(timeout=max(deadline - time.time(), 0.1))
        except subprocess.TimeoutExpired:
            print(f"make ui: services did not stop within {STOP_TIMEOUT_S:.0f} s; killing them", file=sys.stderr)
            break
    _end_group(first.pid)
    return 0 if stopping else (code or 0)


def _end_group(pgid: int) -> None:
    """Whatever the services left behind in their process group (a code server) goes too."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.run.ui", description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=int(os.environ.get("PORT", "3000")))
    parser.add_argument("--host", default="127.0.0.1")
    args = parser.parse_args(argv)
    problem = port_problem(args.host, args.port)
    if problem:
        print(f"make ui: error: {problem}", file=sys.stderr)
        return 2
    try:  # what `make run` runs on: the demo's root while data/raw holds no logs
        choose_demo(False)
        root = data_root_from_env().root_path
        ownership.claim(root, "the data root")  # a folder quadcore did not make gets nothing written into it
    except (SettingError, ownership.ForeignFolderError) as exc:
        print(f"make ui: error: {exc}", file=sys.stderr)
        return 2
    home = ensure_dagster_home(root)
    try:
        cmds = service_commands(args.host, args.port)
    except FileNotFoundError as exc:
        print(f"make ui: error: {exc}", file=sys.stderr)
        return 2
    url = f"http://{args.host}:{args.port}"
    print(f"Starting Dagster's UI on {url} (instance {home}; plots from {root}/plots); it says when it is ready; "
          "Ctrl-C stops it", flush=True)
    return serve(cmds, {**os.environ, "DAGSTER_HOME": str(home), "QUADCORE_DATA_ROOT": str(root)}, url)


if __name__ == "__main__":
    sys.exit(main())
