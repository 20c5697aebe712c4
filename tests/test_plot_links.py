"""Plot links on the asset pages: ``make ui`` serves ``<data root>/plots`` from this machine's
disk, so with an object-store data root the plots stay inline (a link would point at a file the
plot server cannot see)."""

from __future__ import annotations

from pipeline.plot_links import PLOTS_URL_ENV, plot_md
from pipeline.resources import DataRoot

PNG = b"\x89PNG\r\n\x1a\nnot really"


def test_a_local_root_links_its_plot_file(tmp_path, monkeypatch):
    monkeypatch.setenv(PLOTS_URL_ENV, "http://127.0.0.1:3001")
    md = plot_md(DataRoot(root=str(tmp_path)), PNG, "candidates").value
    assert md.startswith("![candidates](http://127.0.0.1:3001/") and md.endswith(".png)")
    assert len(list((tmp_path / "plots").glob("*.png"))) == 1


def test_an_object_store_root_keeps_its_plots_inline(tmp_path, monkeypatch):
    monkeypatch.setenv(PLOTS_URL_ENV, "http://127.0.0.1:3001")
    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:9")  # nothing listens: any S3 request fails
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "x")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "x")
    md = plot_md(DataRoot(root="s3://lab/quadcore"), PNG, "candidates").value
    assert md.startswith("![candidates](data:image/png;base64,")
