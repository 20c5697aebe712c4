"""Plot links on the asset pages: ``make ui`` serves ``<data root>/plots`` from this machine's
disk at ``/quadcore-plots/`` on its own origin, so a link carries no host or port; with an
object-store data root the plots stay inline (a link would point at a file the UI cannot see)."""

from __future__ import annotations

from pipeline.plot_links import PLOTS_ROUTE, plot_md
from pipeline.resources import DataRoot

PNG = b"\x89PNG\r\n\x1a\nnot really"


def test_a_local_root_links_its_plot_file_without_host_or_port(tmp_path):
    md = plot_md(DataRoot(root=str(tmp_path)), PNG, "candidates").value
    assert md.startswith(f"![candidates]({PLOTS_ROUTE}/") and md.endswith(".png)")
    (written,) = (tmp_path / "plots").glob("*.png")
    assert md == f"![candidates]({PLOTS_ROUTE}/{written.name})" and written.read_bytes() == PNG
    assert plot_md(DataRoot(root=str(tmp_path)), PNG, "candidates").value == md  # same plot, same file


def test_the_ui_serves_the_plots_of_its_own_data_root(tmp_path):
    """The route the links use, on the webserver's application: served from the data root the
    UI runs on (a copied root serves its own copy)."""
    from starlette.applications import Starlette
    from starlette.responses import PlainTextResponse
    from starlette.routing import Route
    from starlette.testclient import TestClient

    from pipeline.run.webserver import with_plots

    md = plot_md(DataRoot(root=str(tmp_path / "copy")), PNG, "candidates").value
    app = with_plots(Starlette(routes=[Route("/{path:path}", lambda r: PlainTextResponse("index"))]),
                     tmp_path / "copy" / "plots")
    client = TestClient(app)
    assert client.get(md[md.index("(") + 1:-1]).content == PNG
    assert client.get("/assets/x").text == "index"  # everything else is Dagster's
    assert client.get(f"{PLOTS_ROUTE}/missing.png").status_code == 404


def test_an_object_store_root_keeps_its_plots_inline(tmp_path, monkeypatch):
    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:9")  # nothing listens: any S3 request fails
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "x")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "x")
    md = plot_md(DataRoot(root="s3://lab/quadcore"), PNG, "candidates").value
    assert md.startswith("![candidates](data:image/png;base64,")
