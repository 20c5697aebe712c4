"""The UI for real: `make ui` (`dg dev`) on a loopback port, a materialisation launched through its
GraphQL API, metadata read back; and the asset graph in headless Chromium."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from quadcore.sim import simulation

sys.path.insert(0, str(Path(__file__).parent))
from cdp import Browser, chromium_path, free_port  # noqa: E402

pytestmark = pytest.mark.slow  # dagster dev in a subprocess and a browser

REPO = Path(__file__).resolve().parents[1]
LOCATION = "pipeline.definitions:defs"


@pytest.fixture(scope="module")
def webserver(tmp_path_factory):
    base = tmp_path_factory.mktemp("ui")
    raw = base / "raw"
    simulation.simulate_set(raw, [simulation.SimConfig(kind="hover", duration_s=3.0, seed=s) for s in (1, 2)], {})
    home = base / "dagster_home"
    home.mkdir()
    (home / "dagster.yaml").write_text("telemetry:\n  enabled: false\n")
    port = free_port()
    _populate(base, home, raw.parent / "drag")
    env = {**os.environ, "DAGSTER_HOME": str(home), "QUADCORE_DATA_ROOT": str(base / "root"),
           "QUADCORE_RAW_DIR": str(raw), "QUADCORE_AUTOMATION": "off"}  # only the run the test launches
    proc, log = start_ui(base, home, port, env)
    url = f"http://127.0.0.1:{port}"
    yield url, port, base
    sys.__stderr__.write(f"\nUI screenshots (PNG) kept in {base}\n")  # the test artefacts, for people to look at
    # SIGTERM to the launcher alone (as a service manager would send it) stops every service
    proc.send_signal(signal.SIGTERM)
    try:
        code = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        code = None
    left = _kill_everything_of(home)
    log.close()
    assert code == 0 and not left, f"exit {code}; still running after SIGTERM: {left}"
    from pipeline.run.ui import port_problem

    assert port_problem("127.0.0.1", port) is None


def start_ui(base: Path, home: Path, port: int, env: dict[str, str]):
    """`make ui`'s launcher on ``port``, its output in ``base/dagster_dev.log``, in a session of
    its own (so that a failed test can still end everything); (process, log file) once it answers."""
    log = open(base / "dagster_dev.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.run.ui", "--port", str(port)],
                            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.time() + 180
    while True:
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/server_info", timeout=2)
            return proc, log
        except Exception:
            if proc.poll() is not None or time.time() > deadline:
                _kill_everything_of(home)
                pytest.fail(f"make ui did not start: {(base / 'dagster_dev.log').read_text()[-2000:]}")
            time.sleep(1)


def _populate(base: Path, home: Path, raw: Path) -> None:
    """What a lab has before opening the UI: three flights with rotor drag hidden, decoded and
    checked, the model diagnosed nominal, then with rotor_drag added (the error falls)."""
    import dagster as dg

    from pipeline.assets import AGAINST_MODEL, FLEET
    from pipeline.assets.decode import decoded_flight
    from pipeline.resources import DataRoot, ModelConfig

    configs = [simulation.SimConfig(kind="random", duration_s=5.0, seed=s) for s in (31, 32, 33)]
    simulation.simulate_set(raw, configs, {"rotor_drag": {"k_x_s_per_m": 0.15, "k_y_s_per_m": 0.15}})
    data_root = DataRoot(root=str(base / "root"), raw=str(raw))
    quiet = {"loggers": {"console": {"config": {"log_level": "ERROR"}}}}
    # plots are linked as /quadcore-plots/<file>, served by `make ui` on whatever port it runs
    instance = dg.DagsterInstance.from_config(str(home))
    keys = sorted(p.name for p in raw.iterdir() if not p.name.endswith(".json"))
    instance.add_dynamic_partitions("flights", keys)
    for key in keys:
        assert dg.materialize([decoded_flight], partition_key=key, instance=instance, run_config=quiet,
                              resources={"data_root": data_root}).success
    for effects in ("", "rotor_drag"):
        assert dg.materialize(FLEET, instance=instance, run_config=quiet,
                              resources={"data_root": data_root, "model": ModelConfig(effects=effects)}).success
    assert dg.materialize(AGAINST_MODEL, partition_key=keys[0], instance=instance, run_config=quiet,
                          resources={"data_root": data_root, "model": ModelConfig(effects="rotor_drag")}).success
    instance.dispose()


def _kill_everything_of(home: Path) -> list[str]:
    """Kill the processes started for this Dagster home (found by their environment); their command lines."""
    left = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        try:
            if f"DAGSTER_HOME={home}".encode() not in environ.read_bytes().split(b"\0"):
                continue
            pid = int(environ.parent.name)
            left.append((environ.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"))
            os.kill(pid, signal.SIGKILL)
        except (OSError, ValueError):
            continue
    return left


def test_a_taken_port_is_one_clear_line(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        env = {**{k: v for k, v in os.environ.items() if not k.startswith("QUADCORE_")},
               "DAGSTER_HOME": str(tmp_path / "home"), "QUADCORE_DATA_ROOT": str(tmp_path / "root")}
        done = subprocess.run([sys.executable, "-m", "pipeline.run.ui", "--port", str(port)], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    # the command to type, with the settings in use (the data root and the instance of this one)
    assert done.stderr.strip() == (f"make ui: error: port {port} on 127.0.0.1 is already in use; choose another: "
                                   f"QUADCORE_DATA_ROOT={tmp_path / 'root'} DAGSTER_HOME={tmp_path / 'home'} "
                                   f"PORT={port + 1} make ui")
    assert not (tmp_path / "home").exists()  # nothing started, nothing written


def test_make_ui_says_when_the_ui_answers(webserver):
    """The URL is printed at once, with the instance and plots folder; that the UI answers is said
    when it does (seconds on an idle machine, a minute on a loaded one), with the URL to open."""
    url, _, base = webserver
    deadline = time.time() + 30  # the launcher polls every half second once the UI answers
    while "make ui: ready after" not in (text := (base / "dagster_dev.log").read_text()) and time.time() < deadline:
        time.sleep(0.5)
    assert f"Starting Dagster's UI on {url} (instance " in text
    assert re.search(rf"make ui: ready after \d+ s: open {re.escape(url)}\n", text), text[-2000:]


def test_materialise_through_graphql_and_read_metadata(webserver):
    from dagster_graphql import DagsterGraphQLClient

    url, port, _ = webserver
    client = DagsterGraphQLClient("127.0.0.1", port_number=port)
    repo = {"repositoryLocationName": LOCATION, "repositoryName": "__repository__"}
    added = client._execute(
        """mutation($repo: RepositorySelector!, $key: String!) {
             addDynamicPartition(repositorySelector: $repo, partitionsDefName: "flights", partitionKey: $key) {
               __typename } }""", {"repo": repo, "key": "sim001"})
    assert added["addDynamicPartition"]["__typename"] in ("AddDynamicPartitionSuccess",
                                                         "DuplicateDynamicPartitionError")
    run_id = client.submit_job_execution("process_flight", repository_location_name=LOCATION,
                                         repository_name="__repository__", tags={"dagster/partition": "sim001"})
    deadline = time.time() + 240
    while (status := client.get_run_status(run_id).value) not in ("SUCCESS", "FAILURE", "CANCELED"):
        assert time.time() < deadline, f"run {run_id} still {status}"
        time.sleep(2)
    assert status == "SUCCESS"
    result = client._execute(
        """query($key: AssetKeyInput!, $p: [String!]) { assetOrError(assetKey: $key) { ... on Asset {
             assetMaterializations(partitions: $p, limit: 5) { runId partition metadataEntries { label
               ... on FloatMetadataEntry { floatValue } ... on MarkdownMetadataEntry { mdStr } } } } } }""",
        {"key": {"path": ["residual_table"]}, "p": ["sim001"]})
    mats = [m for m in result["assetOrError"]["assetMaterializations"] if m["runId"] == run_id]
    assert mats and mats[0]["partition"] == "sim001"
    entries = {e["label"]: e for e in mats[0]["metadataEntries"]}
    assert 0 < entries["force_rmse_x_N"]["floatValue"] < 0.01  # a hover without effects: noise level
    # a short link (under the 1,000 characters the asset page renders inline) with no host or port,
    # served by the UI on its own origin
    link = entries["model_vs_measured"]["mdStr"]
    assert len(link) < 1000 and link.startswith("![model vs measured](/quadcore-plots/"), link
    with urllib.request.urlopen(url + link[link.index("(") + 1:-1], timeout=10) as response:
        assert response.read(8) == b"\x89PNG\r\n\x1a\n"


@pytest.mark.skipif(chromium_path() is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_asset_graph_in_headless_chromium(webserver):
    url, _, base = webserver
    browser = Browser(base / "chromium-profile")
    try:
        browser.goto(f"{url}/locations/{LOCATION}/asset-groups/physics")
        browser.wait_for("document.body && document.body.innerText.includes('rollout_errors') "
                         "&& /partitions? *$/im.test(document.body.innerText)", 90)
        # dismiss the first-visit newsletter dialog if it is there
        browser.js("(() => { const b = [...document.querySelectorAll('button')].find(x => x.innerText.trim() === "
                   "'Skip'); if (b) b.click(); })()")
        time.sleep(1.5)
        text = browser.js("document.body.innerText")
        shot = browser.screenshot(base / "asset_graph.png")
    finally:
        browser.close()
    for name in ("residual_table", "rollout_errors", "decoded_flight", "physics_model"):
        assert name in text
    assert "partition" in text.lower()
    from PIL import Image

    img = Image.open(shot)
    assert img.size[0] >= 1200 and len(img.convert("RGB").getcolors(1 << 20) or []) > 50  # a real page, not blank
    out = os.environ.get("QUADCORE_SCREENSHOT_DIR")
    if out:  # keep it for people to look at (CI artefact)
        Path(out).mkdir(parents=True, exist_ok=True)
        Path(out, "asset_graph.png").write_bytes(shot.read_bytes())


SKIP_DIALOG = ("(() => { const b = [...document.querySelectorAll('button')].find(x => x.innerText.trim() === 'Skip');"
               " if (b) b.click(); })()")


def _page(webserver, path: str, ready: str, name: str, then: str = "", then_ready: str = "") -> tuple[str, Path]:
    """Open ``path`` in headless Chromium, wait until ``ready`` holds, run ``then`` (scroll, click)
    and wait for ``then_ready``, screenshot it; returns (the page's text, the screenshot)."""
    url, _, base = webserver
    browser = Browser(base / f"chromium-{name}")
    try:
        browser.goto(f"{url}{path}")
        browser.wait_for(ready, 120)
        time.sleep(2.0)  # the first-visit newsletter dialog comes a moment after the page: dismiss it
        browser.js(SKIP_DIALOG)
        if then:
            browser.js(then)
            browser.wait_for(then_ready or "true", 60)
        time.sleep(1.0)
        browser.js(SKIP_DIALOG)
        time.sleep(0.5)
        text = browser.js("document.body.innerText")
        shot = browser.screenshot(base / f"{name}.png")
    finally:
        browser.close()
    out = os.environ.get("QUADCORE_SCREENSHOT_DIR")
    if out:  # keep it for people to look at (CI artefact)
        Path(out).mkdir(parents=True, exist_ok=True)
        Path(out, f"{name}.png").write_bytes(shot.read_bytes())
    return text, shot


def _scroll_to_image(alt: str) -> str:
    return f"[...document.images].find(i => i.alt === {alt!r}).scrollIntoView({{block: 'center'}})"


def _image_shown(alt: str) -> str:
    """JS: an <img alt=...> on the page, loaded (from the plots server) and laid out (not behind a click)."""
    return (f"[...document.images].some(i => i.alt === {alt!r} && i.complete && i.naturalWidth > 200 "
            f"&& i.getBoundingClientRect().width > 200)")


@pytest.mark.skipif(chromium_path() is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_diagnosis_page_shows_its_plot(webserver):
    """On a port that is not the default one: the plots are linked without host or port and
    served by the UI itself."""
    url, port, _ = webserver
    assert port != 3000
    text, shot = _page(webserver, "/assets/model_diagnosis", _image_shown("candidates"), "diagnosis",
                       _scroll_to_image("candidates"))
    assert "verdict" in text.lower() and "nominal+rotor_drag" in text
    assert "headline" in text and "next_step" in text
    assert _colours(shot) > 200  # a real plot on the page, not a blank frame
    top, _ = _page(webserver, "/assets/model_diagnosis",
                   "document.body && document.body.innerText.includes('next_step')", "diagnosis_top")
    assert "Add 'rotor_drag' to `effects` in" in top or "Nothing in the library to add" in top


@pytest.mark.skipif(chromium_path() is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_a_flight_page_shows_its_plot(webserver):
    text, shot = _page(webserver, "/assets/residual_table?view=partitions&partition=sim000",
                       _image_shown("model vs measured"), "flight_residual_table",
                       _scroll_to_image("model vs measured"))
    assert "sim000" in text
    assert _colours(shot) > 200


@pytest.mark.skipif(chromium_path() is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_the_retraining_schedule_is_listed_with_its_cron(webserver):
    text, _ = _page(webserver, "/automation",
                    "document.body && document.body.innerText.includes('nightly_retrain_learned_models')",
                    "schedule")
    assert "nightly_retrain_learned_models" in text and "raw_log_sensor" in text


@pytest.mark.skipif(chromium_path() is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_error_history_is_a_falling_step_chart_per_evaluation_set(webserver):
    from quadcore.identify import history

    _, _, base = webserver
    sets = history.series(history.read(base / "root"))
    (name, rows), = sets.items()  # nominal, then nominal+rotor_drag, on the same flights: one series
    assert rows["model_label"].to_list() == ["nominal", "nominal+rotor_drag"]
    assert rows["force_rmse_x_N"][1] < 0.5 * rows["force_rmse_x_N"][0]  # the step falls
    text, shot = _page(webserver, "/assets/error_history", _image_shown("history"), "error_history",
                       _scroll_to_image("history"))
    assert "nominal+rotor_drag" in text
    assert _colours(shot) > 200


@pytest.mark.skipif(chromium_path() is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_check_table_names_the_flights(webserver):
    """The check's latest result names its flight; its 'flights' table lists every flight's outcome."""
    open_table = ("[...document.querySelectorAll('a, button')].find(x => x.textContent.trim() === '[Show Markdown]')"
                  ".click()")
    text, _ = _page(webserver, "/assets/decoded_flight?view=checks",
                    "document.body && document.body.innerText.includes('[Show Markdown]')", "checks",
                    open_table, "document.body.innerText.includes('sim002')")
    for name in ("stuck_sensors", "sample_gaps"):
        assert name in text
    assert "all 3 flights pass" in text  # the check speaks for every flight, with the count
    table = text[text.rindex("flight\toutcome\treason"):]
    assert all(f"{fid}\tpass" in table for fid in ("sim000", "sim001", "sim002")), table


def _colours(shot: Path) -> int:
    from PIL import Image

    return len(Image.open(shot).convert("RGB").getcolors(1 << 20) or [])

