"""Plots on the asset page without a click, on whatever port the UI runs.

Dagster's asset page renders a Markdown metadata value inline only when it is shorter than 1,000
characters; a PNG inline as base64 is far longer, so it hides behind "[Show Markdown]". So each
plot is written once under ``<data root>/plots/<content hash>.png`` and the metadata is a short
Markdown image link to ``/quadcore-plots/<file>``: a path with no host or port, resolved by the
browser against the UI's own page and served by the UI process from its own data root
(:mod:`pipeline.run.webserver`, what ``make ui`` runs). The link stays right on any port, after a
restart, and on a copy of the data root. With an object-store data root (the UI serves this
machine's disk) the PNG stays inline (one click, but nothing to serve).
"""

import hashlib

import dagster as dg

from pipeline.resources import DataRoot
from quadcore.report import render
from quadcore.store import store

PLOTS_FOLDER = "plots"
PLOTS_ROUTE = "/quadcore-plots"  # pipeline.run.webserver serves <data root>/plots there


def plot_md(data_root: DataRoot, png: bytes, alt: str) -> dg.MetadataValue:
    """A plot as Markdown metadata: a link to its file under :data:`PLOTS_ROUTE`, or the PNG
    inline for an object-store data root."""
    if store.is_remote(data_root.root_path):  # make ui serves plots from this disk only
        return dg.MetadataValue.md(render.markdown_image(png, alt))
    name = f"{hashlib.sha256(png).hexdigest()[:20]}.png"  # same plot, same file: reruns add nothing
    path = data_root.root_path / PLOTS_FOLDER / name
    if not path.is_file():
        store.write_bytes(png, path)
    return dg.MetadataValue.md(f"![{alt}]({PLOTS_ROUTE}/{name})")


# Significant digits of the numbers shown in the UI (more is noise: 0.004821921990655964).
DIGITS = 4


def number(value: float) -> dg.MetadataValue:
    """A float for the UI, rounded to ``DIGITS`` significant digits (still plotted over time)."""
    return dg.MetadataValue.float(float(f"{float(value):.{DIGITS}g}"))
