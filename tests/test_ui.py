"""The UI for real: `make ui` (`dg dev`) on a loopback port, a materialisation launched through its
GraphQL API, metadata read back; and the asset graph in headless Chromium."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from quadcore import simulation

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
    port, plots_port = free_port(), free_port()
    env = {**os.environ, "DAGSTER_HOME": str(home), "QUADCORE_DATA_ROOT": str(base / "root"),
           "QUADCORE_RAW_DIR": str(raw), "QUADCORE_AUTOMATION": "off"}  # only the run the test launches
    log = open(base / "dagster_dev.log", "w")
    # `make ui`'s launcher; its own session too, so that a failed test can still end everything
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.ui", "--port", str(port), "--plots-port", str(plots_port)],
                            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.time() + 180
    while True:
        try:
            urllib.request.urlopen(f"{url}/server_info", timeout=2)
            break
        except Exception:
            if proc.poll() is not None or time.time() > deadline:
                _kill_everything_of(home)
                pytest.fail(f"make ui did not start: {(base / 'dagster_dev.log').read_text()[-2000:]}")
            time.sleep(1)
    yield url, port, base
    # SIGTERM to the launcher alone (as a service manager would send it) stops every service
    proc.send_signal(signal.SIGTERM)
    try:
        code = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        code = None
    left = _kill_everything_of(home)
    log.close()
    assert code == 0 and not left, f"exit {code}; still running after SIGTERM: {left}"
    from pipeline.ui import port_problem

    assert port_problem("127.0.0.1", port) is None


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
        env = {**os.environ, "DAGSTER_HOME": str(tmp_path / "home"), "QUADCORE_DATA_ROOT": str(tmp_path / "root")}
        done = subprocess.run([sys.executable, "-m", "pipeline.ui", "--port", str(port)], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip() == (f"make ui: error: port {port} on 127.0.0.1 is already in use; "
                                   f"choose another with PORT={port + 1} make ui")
    assert not (tmp_path / "home").exists()  # nothing started, nothing written


def test_materialise_through_graphql_and_read_metadata(webserver):
    from dagster_graphql import DagsterGraphQLClient

    _, port, _ = webserver
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
    # a short link (under the 1,000 characters the asset page renders inline) to the served PNG
    link = entries["model_vs_measured"]["mdStr"]
    assert len(link) < 1000 and link.startswith("![model vs measured](http://127.0.0.1:"), link
    with urllib.request.urlopen(link[link.index("(") + 1:-1], timeout=10) as response:
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
