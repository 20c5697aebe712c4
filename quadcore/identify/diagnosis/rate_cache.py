"""The rate level's per-flight sums kept under the data root, so that a diagnosis after one more
flight reads that flight's rows only (:func:`stored`, the ``cache`` of
:func:`quadcore.identify.rates.judge`).

A diagnosis with timing candidates reduces every flight's rows to its
:class:`~quadcore.identify.rates.RateSums` (or finds it logged below the command rate,
:class:`~quadcore.identify.rates.BelowCommandRate`). Those depend on the flight's log, on what
:func:`quadcore.identify.rates.flight_inputs` names (the timing candidates, the start left out,
the model on the flight: its vehicle, its effects, and the values of those that are not linear)
and on the code. Each flight keeps the last ones made, in ``<root>/stats/flight=<id>/rates.bin``
(:mod:`quadcore.identify.binfile`'s format, written atomically), under a key of all of these
(:func:`key`): a diagnosis of the same candidates against a model with the same effects (the
nominal one, or a refit that moved only the values of its linear effects: the sums hold those as
columns, :attr:`quadcore.identify.rates.RateSums.model`, taken out at the values of the diagnosis's
model) reads them back bit for bit; any other (a refit that moved a nonlinear effect of the model,
such as ``motor_lag``'s τ, a log decoded again, other code, another format) does not match the key,
and the flight's sums are computed from its rows again and replace them. A file that cannot be
read (cut short, not one) is computed again too, never read. Without a data root (``quadcore
diagnose`` on logs) nothing is kept.

Not in ``stats.bin``: the flight's statistics do not depend on the fitted model, the rate
level's do (the model's nonlinear effects' torque is taken out of the increments before the sums).
"""

from __future__ import annotations

import functools
import hashlib
import json
from typing import Any

import numpy as np

from quadcore import effects as effectlib
from quadcore.identify import binfile, rates
from quadcore.identify.stats import sufficient
from quadcore.store import codedigest, store
from quadcore.store.names import check_component

# bump when what the file holds changes: kept ones become stale (2: the unwhitened totals, 3: blocks,
# 4: the lagged blocks, 5: the model's linear effects as columns, RateSums.model)
FORMAT = 5
FILE = "rates.bin"
# The code the sums come from besides the statistics' (sufficient.CODE_MODULES: the rows, the
# state, the effects' base, the grids' interpolation in profiles): the rate level's modules that
# make what it keeps of a flight (not its comparison or judgement, which read the sums) and this file.
CODE_MODULES = ("quadcore.identify.rates.increments", "quadcore.identify.rates.noise", "quadcore.identify.rates.sums",
                "quadcore.identify.diagnosis.rate_cache")


def path(root: Any, flight: str) -> Any:
    return store.as_root(root) / "stats" / f"flight={check_component(flight, 'flight id')}" / FILE


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """The source of the statistics' modules (:data:`quadcore.identify.stats.sufficient.CODE_MODULES`)
    and of :data:`CODE_MODULES` (once per process)."""
    return codedigest.modules_digest((*sufficient.CODE_MODULES, *CODE_MODULES))


def key(source: str, inputs: dict) -> str:
    """What a flight's kept sums were made for: its log (``source``, the SHA-256), ``inputs``
    (:func:`quadcore.identify.rates.flight_inputs`), the source of each effect they name and the
    code (:func:`code_digest`), in this format."""
    names = [*inputs["timing"], *(name for name, _ in inputs["terms"])]
    content = {"format": FORMAT, "code": code_digest(), "source": source, "inputs": inputs,
               "effects": {n: sufficient.source_digest(type(effectlib.get(n))) for n in names}}
    text = json.dumps(content, sort_keys=True, default=lambda a: np.asarray(a).tolist())
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save(root: Any, flight: str, k: str, sums: rates.FlightRates) -> Any:
    """Write a flight's rate-level sums for key ``k`` (atomically: a kill leaves the old file or the new)."""
    header: dict[str, Any] = {"flight": flight, "key": k, "format": FORMAT}
    if isinstance(sums, rates.BelowCommandRate):
        return binfile.write_file(path(root, flight), {**header, "below_command_rate": [sums.period_s, sums.hold_s]},
                                  {})
    header.update(slots={n: [sl.start, sl.stop] for n, sl in sums.slots.items()}, samples=sums.samples,
                  dt_s=sums.dt_s, n=sums.n, model=list(sums.model))  # not RateSums.at: the model's values
    arrays = {**{f"grid:{n}": g for n, g in sums.grids.items()}, "blocks": sums.blocks, "total": sums.total,
              "noise": sums.noise, "unwhitened": sums.total if sums.unwhitened is None else sums.unwhitened}
    if sums.unwhitened_blocks is not None:  # absent: the same as the blocks (no whitening filter)
        arrays["unwhitened_blocks"] = sums.unwhitened_blocks
    if sums.lagged_blocks is not None:  # absent: no whitening filter (RateSums.lagged_blocks)
        arrays["lagged_blocks"] = sums.lagged_blocks
    return binfile.write_file(path(root, flight), header, arrays)


def load(root: Any, flight: str, k: str) -> rates.FlightRates | None:
    """A flight's kept sums if they were made for key ``k``, else None; :class:`~quadcore.identify.binfile.StatsError`
    when the file is not one."""
    where = path(root, flight)
    try:
        header, array = binfile.decode(binfile.read_file(where))
        binfile.require_format(header, FORMAT)
        if header["key"] != k:
            return None
        if "below_command_rate" in header:
            period, hold = header["below_command_rate"]
            return rates.BelowCommandRate(float(period), float(hold))
        slots = {n: slice(int(a), int(b)) for n, (a, b) in header["slots"].items()}
        return rates.RateSums({n: array(f"grid:{n}") for n in slots}, slots, array("blocks"), array("total"),
                              array("noise"), int(header["samples"]), float(header["dt_s"]), int(header["n"]),
                              array("unwhitened"),
                              array("unwhitened_blocks") if "unwhitened_blocks" in header["arrays"] else None,
                              array("lagged_blocks") if "lagged_blocks" in header["arrays"] else None,
                              tuple(str(m) for m in header["model"]), np.zeros(len(header["model"])))
    except (ValueError, KeyError, TypeError) as exc:
        raise binfile.StatsError(f"{where}: not a rate-level file ({exc})") from None


def stored(root: Any) -> rates.RatesCache:
    """The ``cache`` of :func:`quadcore.identify.rates.judge` under the data root: a flight's kept
    sums when they were made for its log as decoded there and for these inputs (:func:`key`), else
    computed and kept. A flight not decoded under the root (no log digest to key by) is computed,
    not kept."""

    def cached(flight: str, inputs: dict, compute) -> rates.FlightRates:
        source = sufficient.decoded_source(root, flight)
        if not source:
            return compute()
        k = key(source, inputs)
        kept = binfile.read_if_present(path(root, flight), lambda: load(root, flight, k))
        if kept is not None:
            return kept
        out = compute()
        save(root, flight, k, out)
        return out

    return cached
