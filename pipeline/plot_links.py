"""Plots on the asset page without a click.

Dagster's asset page renders a Markdown metadata value inline only when it is shorter than 1,000
characters; a PNG inline as base64 is far longer, so it hides behind "[Show Markdown]". With
``QUADCORE_PLOTS_URL`` set (``make ui`` serves ``<data root>/plots`` there, ``make run`` points
at the same address), each plot is written once under ``<data root>/plots/<content hash>.png``
and the metadata is a short Markdown image link, which the page shows directly. Without it, or with
an object-store data root (the plot server serves this machine's disk), the PNG stays inline
(one click, but no server needed).
"""

import hashlib
import os

import dagster as dg

from pipeline.resources import DataRoot
from quadcore.report import render
from quadcore.store import store

PLOTS_URL_ENV = "QUADCORE_PLOTS_URL"
PLOTS_FOLDER = "plots"


def plot_md(data_root: DataRoot, png: bytes, alt: str) -> dg.MetadataValue:
    """A plot as Markdown metadata: a link to its file under the plots URL, else the PNG inline."""
    url = os.environ.get(PLOTS_URL_ENV, "").rstrip("/")
    if not url or store.is_remote(data_root.root_path):  # make ui serves plots from this disk only
        return dg.MetadataValue.md(render.markdown_image(png, alt))
    name = f"{hashlib.sha256(png).hexdigest()[:20]}.png"  # same plot, same file: reruns add nothing
    path = data_root.root_path / PLOTS_FOLDER / name
    if not path.is_file():
        store.write_bytes(png, path)
    return dg.MetadataValue.md(f"![{alt}]({url}/{name})")


# Significant digits of the numbers shown in the UI (more is noise: 0.004821921990655964).
DIGITS = 4


def number(value: float) -> dg.MetadataValue:
    """A float for the UI, rounded to ``DIGITS`` significant digits (still plotted over time)."""
    return dg.MetadataValue.float(float(f"{float(value):.{DIGITS}g}"))
