"""The project deletes only what it wrote, and a data root never mixes simulated and real flights.

Issue 22: ``quadcore decode LOG --out ~/`` deleted ``~/.bashrc.old``, a ``.config.old/`` tree, a
project's ``.git/.index.old`` and ``docs/.chapter3.tmp``; a mistyped ``QUADCORE_RAW_DIR`` made the
main job simulate demo flights into it and fit them in the real data root."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from quadcore import cli
from quadcore.sim import simulation
from quadcore.store import ownership, safewrite
from quadcore.workflows import demo

REPO = Path(__file__).resolve().parents[1]


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def tree_digest(folder: Path) -> dict[str, str]:
    """Every file and folder under ``folder`` (relative path -> content hash, or 'dir')."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for d in dirnames:
            out[os.path.relpath(os.path.join(dirpath, d), folder)] = "dir"
        for f in filenames:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, folder)] = hashlib.sha256(Path(p).read_bytes()).hexdigest()
    return out


def user_home(base: Path) -> Path:
    """A home folder as a user has one: hidden backups and temp files a sweep by pattern takes."""
    home = base / "home"
    old = time.time() - 3 * safewrite.STALE_AFTER_S
    files = {".bashrc": "export A=1\n", ".bashrc.old": "export A=0\n", ".config.old/app/settings": "x=1\n",
             "project/.git/.index.old": "index\n", "docs/.chapter3.tmp": "draft\n",
             f".notes.{_dead_pid()}.abc123.tmp": "mine\n", ".features-abc123/keep": "mine\n"}
    for name, text in files.items():
        path = home / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for path in home.rglob("*"):
        os.utime(path, (old, old))
    return home


@pytest.fixture(scope="module")
def one_log(tmp_path_factory) -> Path:
    raw = tmp_path_factory.mktemp("raw")
    simulation.simulate_set(raw, [simulation.SimConfig(kind="hover", duration_s=2.0, seed=3)], {})
    (raw / ("sim000" + simulation.TRUTH_SUFFIX)).unlink()  # a log as a user has it
    return raw / "sim000"


def test_decode_into_a_home_folder_is_refused_and_nothing_there_changes(tmp_path, one_log, capsys):
    home = user_home(tmp_path)
    before = tree_digest(home)
    assert cli.main(["decode", str(one_log), "--out", str(home)]) == 2
    err = capsys.readouterr().err
    assert "did not create" in err and str(home) in err and len(err.strip().splitlines()) == 1
    assert tree_digest(home) == before


def test_a_new_out_folder_is_marked_and_a_second_run_uses_it(tmp_path, one_log):
    out = tmp_path / "out"
    cli.main(["decode", str(one_log), "--out", str(out)])
    assert ownership.is_marked(out) and (out / "decoded").is_dir()
    assert ownership.claim(out) == ""  # marked: used as it is


def test_sweep_stays_inside_a_marked_root_and_its_own_names(tmp_path):
    dead = _dead_pid()
    unmarked = tmp_path / "unmarked"
    (unmarked / "decoded").mkdir(parents=True)
    foreign_leftover = unmarked / "decoded" / f".data.parquet.{dead}.abc.tmp"
    foreign_leftover.write_text("x")
    assert safewrite.sweep_stale(unmarked) == [] and foreign_leftover.exists()

    root = tmp_path / "root"
    ownership.claim(root)
    ours = [root / "decoded" / "fixedFrequency" / f".data.parquet.{dead}.k2j4.tmp",
            root / "learned" / f".xgb.{dead}.k2j4.staging", root / f".model.toml.{dead}.x9.tmp"]
    kept = [root / "raw" / f".log.{dead}.abc.tmp",  # the raw logs are the user's: never swept
            root / "decoded" / f".data.parquet.{os.getpid()}.zz.tmp",  # a live writer's
            root / "decoded" / ".bashrc.old", root / "decoded" / ".notes.tmp",  # not a name of ours
            root / "mine" / f".data.parquet.{dead}.abc.tmp"]  # a folder the project does not write
    for p in [*ours, *kept]:
        p.parent.mkdir(parents=True, exist_ok=True)
        (p.mkdir() if p.suffix == ".staging" else p.write_text("x"))
    assert sorted(safewrite.sweep_stale(root)) == sorted(ours)
    assert all(p.exists() for p in kept) and not any(p.exists() for p in ours)


def test_a_root_of_an_earlier_version_is_adopted_and_a_foreign_one_refused(tmp_path):
    old = tmp_path / "old"
    for name in ("decoded/fixedFrequency", "models", "raw", ".dagster"):
        (old / name).mkdir(parents=True)
    (old / "model.toml").write_text("effects = []\n")
    (old / ".quadcore.lock").write_text("")
    assert "adopted" in ownership.claim(old) and ownership.is_marked(old)

    foreign = tmp_path / "foreign"
    (foreign / "decoded").mkdir(parents=True)
    (foreign / "thesis.tex").write_text("x")
    with pytest.raises(ownership.ForeignFolderError, match="thesis.tex"):
        ownership.claim(foreign)
    assert not (foreign / ownership.MARKER).exists()


def _main_job(env: dict, cwd: Path) -> subprocess.CompletedProcess:
    full = {**{k: v for k, v in os.environ.items() if not k.startswith(("QUADCORE_", "DAGSTER_"))},
            "PYTHONPATH": str(REPO), **env}
    return subprocess.run([sys.executable, "-m", "pipeline"], cwd=cwd, env=full, capture_output=True, text=True,
                          timeout=120)


def test_a_mistyped_raw_folder_is_an_error_and_nothing_is_simulated(tmp_path):
    root = tmp_path / "root"
    proc = _main_job({"QUADCORE_DATA_ROOT": str(root), "QUADCORE_RAW_DIR": str(tmp_path / "logz")}, tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"error: the raw log folder {tmp_path / 'logz'} does not exist: "
                                                "check QUADCORE_RAW_DIR (the demo runs with `make demo`)"]
    assert not (tmp_path / "logz").exists() and not root.exists()


def test_the_main_job_refuses_a_foreign_data_root(tmp_path, one_log):
    home = user_home(tmp_path)
    before = tree_digest(home)
    proc = _main_job({"QUADCORE_DATA_ROOT": str(home), "QUADCORE_RAW_DIR": str(one_log.parent)}, tmp_path)
    assert proc.returncode == 2 and "did not create" in proc.stderr
    assert tree_digest(home) == before


def test_simulated_and_real_flights_never_share_a_root(tmp_path):
    raw = tmp_path / "raw"
    simulation.simulate_set(raw, [simulation.SimConfig(kind="hover", duration_s=2.0, seed=s) for s in (1, 2)], {})
    (raw / ("sim001" + simulation.TRUTH_SUFFIX)).unlink()  # sim001 now looks like a user's log
    logs = sorted(p for p in raw.iterdir() if not p.name.endswith(".json"))
    root = tmp_path / "root"
    ownership.claim(root)
    with pytest.raises(demo.MixedFlightsError, match="sim000.*sim001.*QUADCORE_ALLOW_SIMULATED"):
        demo.check_flight_kinds(root, logs, allow_mixed=False, demo=False)
    assert demo.check_flight_kinds(root, logs, allow_mixed=True, demo=False) == "mixed"
    # a root that holds simulated flights (the demo's) takes no real ones later, and the reverse
    sim_root, real_root = tmp_path / "sim_root", tmp_path / "real_root"
    for r, kind in ((sim_root, "simulated"), (real_root, "real")):
        ownership.claim(r)
        ownership.record_flights_kind(r, kind)
    with pytest.raises(demo.MixedFlightsError):
        demo.check_flight_kinds(sim_root, [raw / "sim001"], allow_mixed=False, demo=False)
    with pytest.raises(demo.MixedFlightsError):
        demo.check_flight_kinds(real_root, [raw / "sim000"], allow_mixed=False, demo=False)
    with pytest.raises(demo.MixedFlightsError, match="demo"):
        demo.check_flight_kinds(real_root, [], allow_mixed=False, demo=True)


def test_the_demo_runs_in_its_own_root_only_on_the_default_one(tmp_path, monkeypatch):
    from pipeline.resources import SettingError, choose_demo

    monkeypatch.chdir(tmp_path)
    for name in ("QUADCORE_DATA_ROOT", "QUADCORE_RAW_DIR"):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / "data" / "raw").mkdir(parents=True)
    assert choose_demo(False) and os.environ["QUADCORE_DATA_ROOT"] == str(tmp_path / "data" / "demo")
    monkeypatch.delenv("QUADCORE_DATA_ROOT")
    (tmp_path / "data" / "raw" / "jana00").write_bytes(b"log")  # the user's own flight: the main job
    assert not choose_demo(False) and "QUADCORE_DATA_ROOT" not in os.environ
    (tmp_path / "data" / "raw" / "jana00").unlink()
    monkeypatch.setenv("QUADCORE_RAW_DIR", str(tmp_path / "logz"))  # a raw folder named: never the demo
    assert not choose_demo(False)
    with pytest.raises(SettingError, match="QUADCORE_RAW_DIR"):
        choose_demo(True)


def test_symlinks_are_followed_only_inside_the_raw_folder(tmp_path, one_log, capsys):
    raw, elsewhere = tmp_path / "raw", tmp_path / "elsewhere"
    raw.mkdir()
    elsewhere.mkdir()
    (raw / "jana01").write_bytes(one_log.read_bytes())
    (raw / "jana02").symlink_to(raw / "jana01")  # inside the raw folder: followed
    (elsewhere / "secret").write_bytes(one_log.read_bytes())
    (raw / "jana03").symlink_to(elsewhere / "secret")  # out of it: not followed, quarantined with the reason
    assert cli.main(["decode", str(raw), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "out" / "decoded" / "fixedFrequency" / "flight=jana02").is_dir()
    assert not (tmp_path / "out" / "decoded" / "fixedFrequency" / "flight=jana03").exists()
    assert "jana03" in out and "outside its folder" in out


def test_the_plots_are_served_without_a_listing_of_their_folder(tmp_path):
    from starlette.applications import Starlette
    from starlette.testclient import TestClient

    from pipeline.plot_links import PLOTS_ROUTE
    from pipeline.run.webserver import with_plots

    (tmp_path / "a.png").write_bytes(b"png")
    client = TestClient(with_plots(Starlette(), tmp_path))
    assert client.get(f"{PLOTS_ROUTE}/a.png").content == b"png"
    for path in (f"{PLOTS_ROUTE}/", f"{PLOTS_ROUTE}/.", PLOTS_ROUTE):
        assert client.get(path).status_code == 404


SLOW_TO_STOP = """import signal, sys, time
def stop(*_):
    time.sleep(2.0)
    sys.exit(0)
signal.signal(signal.SIGINT, stop)
print("ready", flush=True)
while True:
    time.sleep(0.1)
"""


def test_sigterm_lets_the_services_stop_and_says_nothing_untrue():
    """SIGTERM to ``make ui``'s launcher: services that take 2 s to stop get them (the launcher
    killed them after its own 1 s poll and said 'did not stop within 20 s')."""
    launcher = ("import sys\nfrom pipeline.run.ui import serve\n"
                f"sys.exit(serve([[sys.executable, '-c', {SLOW_TO_STOP!r}]], {{}}))\n")
    proc = subprocess.Popen([sys.executable, "-c", launcher], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "did not stop" not in err, err
    assert time.monotonic() - t0 >= 1.8  # the services' own 2 s shutdown ran to its end
