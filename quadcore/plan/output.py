"""The plan as other tools read it: the JSON document and the picture.

JSON (``quadcore plan --json``; key order fixed)::

    {"question": {"kind": "separate", "candidates": [A, B]} | {"kind": "parameter", "parameter": "EFFECT.NAME"}
                 | {"kind": "none"},
     "trajectory": PATH | null, "duration_s": S, "limits": {max_speed_mps, max_acc_mps2, max_tilt_deg,
     arena: [6]}, "predicted": {separation_sigma_before, separation_sigma_after} |
     {parameter_std_before, parameter_std_after}, ...}

followed by what explains the numbers (``why``, ``manoeuvre``, ``checked`` limits, ``design``:
the objective's prediction, ``proof``: each explanation flown in the simulator).

The picture: the path seen from above and from the side inside the arena, coloured by speed,
with the stretches where the two explanations' predicted wrenches differ most marked.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from quadcore.store import store  # noqa: E402

DIFFER_SHARE = 0.1  # the share of the flight marked as "where they differ most"


def document_json(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=2, default=float) + "\n"


def write_json(doc: dict[str, Any], path: str | Path) -> Path:
    return store.write_text(document_json(doc), Path(path))


def plot_png(p_w_m: np.ndarray, speed_mps: np.ndarray, differ: np.ndarray | None, arena: tuple, title: str,
             differ_label: str = "where they differ most") -> bytes:
    """PNG bytes of the planned path (``p_w_m`` (n, 3), ``speed_mps`` (n,)), with ``differ`` (n,)
    (how much the explanations differ there, any scale; None for a parameter question: how
    much the parameter shows) marking its largest ``DIFFER_SHARE`` of samples."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6), gridspec_kw={"width_ratios": [1, 1]})
    a = np.asarray(arena, float)
    mark = None
    if differ is not None and np.any(differ > 0):
        mark = differ >= np.quantile(differ, 1 - DIFFER_SHARE)
    sc = None
    for ax, (i, j), names in ((axes[0], (0, 1), ("x [m]", "y [m]")), (axes[1], (0, 2), ("x [m]", "z [m]"))):
        ax.add_patch(plt.Rectangle((a[i], a[j]), a[i + 3] - a[i], a[j + 3] - a[j], fill=False, lw=1.5, ec="0.3"))
        sc = ax.scatter(p_w_m[:, i], p_w_m[:, j], c=speed_mps, s=3, cmap="viridis", vmin=0)
        if mark is not None:
            ax.scatter(p_w_m[mark, i], p_w_m[mark, j], s=18, facecolors="none", edgecolors="crimson", lw=0.6,
                       label=differ_label)
        ax.plot(p_w_m[0, i], p_w_m[0, j], "k^", ms=8, label="start / end (hover)")
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_aspect("equal")
        pad = 0.1
        ax.set_xlim(a[i] - pad, a[i + 3] + pad)
        ax.set_ylim(a[j] - pad, a[j + 3] + pad)
    axes[0].set_title("from above", pad=28)
    axes[1].set_title("from the side", pad=28)
    axes[1].legend(loc="lower center", bbox_to_anchor=(0.5, 1.08), fontsize=8, ncol=2)
    assert sc is not None
    fig.colorbar(sc, ax=axes, label="speed [m/s]", shrink=0.8)
    fig.suptitle(title, fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def write_plot(png: bytes, path: str | Path) -> Path:
    return store.write_bytes(png, Path(path))
