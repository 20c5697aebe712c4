"""The plan as other tools read it: the JSON document and the picture.

JSON (``quadcore plan --json``; key order fixed)::

    {"question": {"kind": "separate", "candidates": [A, B]} | {"kind": "parameter", "parameter": "EFFECT.NAME"}
                 | {"kind": "none"},
     "trajectory": PATH | null, "duration_s": S, "limits": {max_speed_mps, max_acc_mps2, max_tilt_deg,
     arena: [6]}, "predicted": {separation_sigma_before, separation_sigma_after} |
     {parameter_std_before, parameter_std_after}, ...}

followed by what explains the numbers (``why``, ``measured``: the separation and score gap of
the logged flights, ``manoeuvre``, ``checked`` limits, ``design``: the objective's prediction,
whether the flight ``improves`` both, and where it does not decide alone how many ``repeated``
flights would and the ``advice``, ``proof``: each explanation flown in the simulator, ``proof_left_out``:
each explanation whose flight the proof could not use, and why).

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
    return store.write_text(document_json(doc), store.as_root(path))


def plot_png(p_w_m: np.ndarray, speed_mps: np.ndarray, differ: np.ndarray | None, arena: tuple, title: str,
             differ_label: str = "where they differ most", t_s: np.ndarray | None = None) -> bytes:
    """PNG bytes of the planned path (``p_w_m`` (n, 3), ``speed_mps`` (n,) at times ``t_s``) from
    above and from the side, coloured by speed, with ``differ`` (n,) (how much the explanations
    differ there, any scale; for a parameter question how much the parameter shows) marking its
    largest ``DIFFER_SHARE`` of samples; and both along time."""
    fig = plt.figure(figsize=(12, 4.4))
    axes = [fig.add_axes((0.05, 0.14, 0.25, 0.68)), fig.add_axes((0.36, 0.14, 0.25, 0.68))]
    ax_t = fig.add_axes((0.70, 0.14, 0.27, 0.68))
    a = np.asarray(arena, float)
    mark = None
    if differ is not None and np.any(differ > 0):
        mark = differ >= np.quantile(differ, 1 - DIFFER_SHARE)
    sc = None
    for ax, (i, j), names in ((axes[0], (0, 1), ("x [m]", "y [m]")), (axes[1], (0, 2), ("x [m]", "z [m]"))):
        ax.add_patch(plt.Rectangle((a[i], a[j]), a[i + 3] - a[i], a[j + 3] - a[j], fill=False, lw=1.5, ec="0.3"))
        if mark is not None:
            ax.scatter(p_w_m[mark, i], p_w_m[mark, j], s=30, color="crimson", alpha=0.15, lw=0, label=differ_label)
        sc = ax.scatter(p_w_m[:, i], p_w_m[:, j], c=speed_mps, s=2, cmap="viridis", vmin=0)
        ax.plot(p_w_m[0, i], p_w_m[0, j], "k^", ms=8, label="start / end (hover)")
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_aspect("equal")
        ax.set_xlim(a[i] - 0.1, a[i + 3] + 0.1)
        ax.set_ylim(a[j] - 0.1, a[j + 3] + 0.1)
    axes[0].set_title("from above (colour: speed)", fontsize=9)
    axes[1].set_title("from the side", fontsize=9)
    assert sc is not None
    fig.colorbar(sc, ax=axes[1], label="speed [m/s]", shrink=0.8)
    t = np.arange(len(speed_mps)) if t_s is None else t_s
    ax_t.plot(t, speed_mps, color="0.2", lw=1, label="speed [m/s]")
    ax_t.set_xlabel("time [s]")
    ax_t.set_ylabel("speed [m/s]")
    if differ is not None and np.any(differ > 0):
        ax_d = ax_t.twinx()
        ax_d.plot(t, differ / differ.max(), color="crimson", lw=0.6, alpha=0.7)
        ax_d.set_ylabel(differ_label + " (share of max)", color="crimson", fontsize=8)
    ax_t.set_title("along the flight", fontsize=9)
    handles, labels = axes[1].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def write_plot(png: bytes, path: str | Path) -> Path:
    return store.write_bytes(png, store.as_root(path))
