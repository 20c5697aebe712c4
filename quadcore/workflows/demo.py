"""The demo ``make run`` shows on an empty raw folder: simulated flights with a hidden effect,
and the demo's own model file, to which the effect the diagnosis finds is added."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

# The effect hidden in the demo flights, and its true parameters (SI).
DEMO_EFFECT = {"rotor_drag": {"k_x_s_per_m": 0.12, "k_y_s_per_m": 0.12}}


def simulate_demo_flights(raw: Path, log: Callable[[str], None] = print) -> list[Path]:
    """Six simulated flights with ``DEMO_EFFECT`` hidden in them, as uSD logs under ``raw``."""
    from quadcore.sim import simulation

    log(f"No logs in {raw}: simulating 6 demo flights with a hidden effect (see {raw}/*.truth.json) ...")
    written = simulation.simulate_set(raw, simulation.default_flights(seed=0), DEMO_EFFECT)
    return [log_path for log_path, _ in written]


def write_demo_model_file(root: Path, template: str, effects: list[str]) -> Path:
    """The demo's own model file ``<root>/model.toml``: the template's text (the repository's
    model.toml) with its ``effects`` list set to ``effects``."""
    from quadcore.store import store

    text = Path(template).read_text() if template and Path(template).is_file() else "effects = []\n"
    listed = "effects = [" + ", ".join(f'"{e}"' for e in effects) + "]"
    text, n = re.subn(r"(?m)^effects\s*=\s*\[[^\]]*\]", listed, text)
    return store.write_text(text if n else f"{listed}\n{text}", store.own_model_file(root))
