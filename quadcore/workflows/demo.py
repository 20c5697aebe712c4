"""The demo ``make run`` shows on an empty raw folder: simulated flights with a hidden effect,
and the demo's own model file, to which the effect the diagnosis finds is added."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from quadcore.logs.flight import TRUTH_SUFFIX
from quadcore.sim import simulation
from quadcore.store import ownership, store

# The effect hidden in the demo flights, and its true parameters (SI).
DEMO_EFFECT = {"rotor_drag": {"k_x_s_per_m": 0.12, "k_y_s_per_m": 0.12}}


def simulate_demo_flights(raw: Path, log: Callable[[str], None] = print) -> list[Path]:
    """Six simulated flights with ``DEMO_EFFECT`` hidden in them, as uSD logs under ``raw``."""
    log(f"The demo: simulating 6 flights with a hidden effect into {raw} (see {raw}/*.truth.json) ...")
    written = simulation.simulate_set(raw, simulation.default_flights(seed=0), DEMO_EFFECT)
    return [log_path for log_path, _ in written]


def write_demo_model_file(root: Path, template: str, effects: list[str]) -> Path:
    """The demo's own model file ``<root>/model.toml``: the template's text (the repository's
    model.toml) with its ``effects`` list set to ``effects``."""
    text = Path(template).read_text() if template and Path(template).is_file() else "effects = []\n"
    listed = "effects = [" + ", ".join(f'"{e}"' for e in effects) + "]"
    text, n = re.subn(r"(?m)^effects\s*=\s*\[[^\]]*\]", listed, text)
    return store.write_text(text if n else f"{listed}\n{text}", store.own_model_file(root))


# --- simulated and real flights never mix in one data root -----------------------------------

class MixedFlightsError(ValueError):
    """A data root would hold simulated and real flights together, and the user did not ask for it."""


def is_simulated_log(path: str | Path) -> bool:
    """A log the simulator wrote: it has its ground truth (``<log>.truth.json``) beside it."""
    return Path(str(path) + TRUTH_SUFFIX).is_file()


def simulated_in_store(root: Path) -> tuple[list[str], list[str]]:
    """(simulated, real) flights already decoded under ``root``, from each decoded main table's
    source log (simulated when its ground truth is still beside it)."""
    folder = Path(root) / "decoded" / store.MAIN_EVENT
    sim: list[str] = []
    real: list[str] = []
    for table in sorted(folder.glob("flight=*/data.parquet")) if folder.is_dir() else []:
        try:
            source = store.read_metadata(table).get("source_file", "")
        except (OSError, ValueError):
            continue
        (sim if source and is_simulated_log(source) else real).append(table.parent.name.split("=", 1)[1])
    return sim, real


def _named(ids: list[str]) -> str:
    return ", ".join(ids[:3]) + (f", ... ({len(ids)})" if len(ids) > 3 else "")


def check_flight_kinds(root: Path, logs: list[Path], allow_mixed: bool, demo: bool) -> str:
    """The kind of flights (``real``, ``simulated``, ``mixed``) the data root will hold once
    ``logs`` are in it, recorded in its marker; :class:`MixedFlightsError` with the reason and
    the fix where simulated and real flights would meet unless ``allow_mixed``
    (``QUADCORE_ALLOW_SIMULATED=1``). The demo's root holds simulated flights only."""
    sim = [p.name for p in logs if is_simulated_log(p)]
    real = [p.name for p in logs if not is_simulated_log(p)]
    recorded = ownership.flights_kind(root)
    if not recorded and ownership.is_marked(root):  # a root of an earlier version: what it already holds
        held_sim, held_real = simulated_in_store(root)
        sim, real = sorted({*sim, *held_sim}), sorted({*real, *held_real})
    earlier = ["(flights decoded there before)"]
    real = real or (earlier if recorded in ("real", "mixed") else [])
    sim = sim or (earlier if recorded in ("simulated", "mixed") else [])
    if demo and real and not allow_mixed:
        raise MixedFlightsError(
            f"the demo's data root {root} holds flights of your own ({_named(real)}): the demo simulates into a "
            "root of its own; give it another (QUADCORE_DATA_ROOT) or run without --demo")
    if sim and real and not allow_mixed:
        raise MixedFlightsError(
            f"data root {root} would mix simulated flights ({_named(sim)}; simulated: a .truth.json beside the "
            f"log, or the root's marker) with real ones ({_named(real)}): a fit on both describes neither. Give "
            "your flights a data root of their own (QUADCORE_DATA_ROOT=data/mine), or move the simulated logs "
            "out of the raw folder; QUADCORE_ALLOW_SIMULATED=1 mixes them on purpose")
    kind = "mixed" if sim and real else "simulated" if sim else "real"
    if sim or real:
        ownership.record_flights_kind(root, kind)
    return kind
