"""Per-flight statistics of term discovery's candidate library: what
:func:`quadcore.identify.discovery.select.discover` needs of a flight, without its rows.

**The columns.** On a flight's samples the discovery design row is
(:func:`quadcore.identify.discovery.grams.flight_grams`)

    z_i = [F_i | Tq_i | y0_i | m_i | B_i]

``F`` the candidate terms through the force smoother, ``Tq`` through the gyro derivative's
filter, ``y0`` (6) the nominal residual (force N, torque N m, body frame), ``m`` (6) the
modelled thrust and rotor torque, ``B`` every effect's basis per axis (built in, and the
model file's plugins). Per flight we store

    G = Σ_{i ∈ every STRIDE-th usable sample} z_i z_iᵀ,     H = Σ_{i ∈ usable} z_i z_iᵀ,

(``H`` only within the force axes' columns and within the torque axes': the held-out RMSE of a
force axis never takes a torque column; half the products), the usable samples ``n``, the
sensor-noise floor (6,), ``Σ_{i ∈ usable} y0_i²`` (6,) exactly as the rows give it, and the
variables the library is built from (names, units, sources). And ``H``, ``n`` and ``Σ y0²`` once
more over the usable samples after the flight's first ``K`` blocks (:func:`head_blocks`: the
longest memory of the effects the statistics hold, 1 block with the built-in ones): the diagnosis
scores an evaluated flight there (:func:`quadcore.identify.evidence.scored_after_blocks`),
and so does discovery (the model's transform below is linear, so it carries over to them).
About 0.9 MB per flight (331 columns with the built-in effects, 0.67 MB before the sums after the first
blocks: ``benchmarks/bench_discover_stats.py``).

**A model with linear effects.** Discovery works on the residual the model leaves,
``r_a = y0_a - Σ_k θ_k B_{a,k}`` on axis ``a`` (``θ`` the effects' linear coordinates,
:meth:`quadcore.effects.Effect.to_linear`, fitted on the training flights). That is ``r = z T``
with ``T`` the identity but for the residual's columns, ``T[B_{a,k}, y_a] = -θ_k``, so

    G_r = Tᵀ G T,       H_r = Tᵀ H T

exactly (in exact arithmetic; ``T`` mixes columns of one axis only, so ``H``'s two blocks stay
whole): the stored matrices serve every fit of linear effects. A model
with a nonlinear effect, or effects fitted per session, is read from rows: its residual predicted on
them takes ``y0``'s place in the statistics :func:`compute` makes of them (kept in memory, not stored).

Stored under ``<root>/stats/flight=<id>/library.bin`` (the format of
:mod:`quadcore.identify.stats.sufficient`, upper triangles in float64) with the :func:`library_key` they were
computed for and the SHA-256 of the log the decoded table came from.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from quadcore import effects as effectlib
from quadcore.identify import evidence, flightdata
from quadcore.identify.discovery.grams import channel_groups, flight_grams, library_columns
from quadcore.identify.discovery.terms import Term, library, variables
from quadcore.identify.settings import STATISTICS
from quadcore.identify.stats import sufficient
from quadcore.store import codedigest

FORMAT = 3  # bump when what the statistics mean changes: stored ones become stale
STRIDE = STATISTICS.library_stride  # discovery's default: every 4th usable sample in the selection's Gram matrix
# the modules the statistics are computed by (with the sufficient statistics' code: sufficient.code_digest)
_MODULES = ("quadcore.identify.discovery.terms", "quadcore.identify.discovery.grams",
            "quadcore.identify.discovery.library_stats")


@dataclass(frozen=True)
class FlightLibrary:
    """One flight's discovery statistics (see the module); the two Gram matrices are read when
    :meth:`grams` is called (a stored file is read again each time: a thousand flights' matrices
    are never all in memory)."""

    flight: str
    key: str
    source: str  # SHA-256 of the log the decoded table came from
    variables: tuple[tuple[str, tuple[int, ...], tuple[str, ...], str], ...]  # name, unit, sources, channel
    labels: tuple[str, ...]  # a name per Gram column (grams.Columns.labels)
    samples: int
    noise: np.ndarray  # (6,)
    y0_squares: np.ndarray  # (6,) Σ over usable samples of y0² (of the residual ``compute`` was given)
    head_blocks: int  # K: the first blocks the "after" sums leave out (head_blocks())
    samples_after: int  # the usable samples after them
    y0_squares_after: np.ndarray  # (6,) Σ of y0² over those
    grams_source: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]

    def grams(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(G, H, H_after): every ``STRIDE``-th usable sample's, every usable sample's, and the
        usable samples' after the first ``head_blocks`` blocks."""
        return self.grams_source()

    @property
    def logs_motors(self) -> bool:
        return any(name.startswith("motor_") for name, *_ in self.variables)


def fx_effects(spec) -> list[effectlib.Effect]:
    """The effects whose bases the statistics hold: the built-in ones, then the model file's
    plugins (the order of :func:`quadcore.effects.registry`)."""
    builtin = effectlib.builtin_names()
    return [effectlib.get(n) for n in [*builtin, *sorted(n for n in spec.effects if n not in builtin)]]


def head_blocks(spec) -> int:
    """``K``, the first blocks of a flight whose sums the statistics also hold apart: within the
    longest memory of the effects they hold (:func:`quadcore.identify.evidence.memory_blocks` of
    :func:`fx_effects`), as many as a diagnosis offering them leaves out of its scores."""
    return evidence.memory_blocks(fx_effects(spec))


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """The source of the modules the sufficient statistics and the discovery statistics are
    computed by (once per process, as :func:`quadcore.identify.stats.sufficient.code_digest`)."""
    return codedigest.modules_digest((*sufficient.CODE_MODULES, *_MODULES))


def library_key(spec, flight: str) -> str:
    """What a flight's statistics were computed for: the model's vehicle and the flight's own,
    the stride, the effects' names and sources, the code (stored ones with another are stale)."""
    content = {"format": FORMAT, "stride": STRIDE, "code": _code_digest(),
               "vehicle": sufficient.stats_key(spec.vehicle, spec.vehicle_for(flight), sufficient.Layout((), ())),
               "effects": {e.name: sufficient.source_digest(type(e)) for e in fx_effects(spec)}}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16]


def version(spec, flight: str) -> str:
    """The version of everything the statistics asset stores for a flight: its sufficient
    statistics' key and this key."""
    return f"{sufficient.current_key(spec, flight)}+{library_key(spec, flight)}"


def compute(spec, flight: str, decoded, source: str = "", fd: flightdata.FlightData | None = None,
            residual: np.ndarray | None = None, terms: list[Term] | None = None, stride: int = STRIDE,
            blocks: int | None = None) -> FlightLibrary:
    """A flight's statistics from its decoded table (its rows read once): the one place a flight's
    rows become discovery's sums. ``fd``: the table's :func:`quadcore.identify.flightdata.flight_data`
    when the caller has it (the effects' bases cached there are not computed again); ``residual``
    (n, 6): the residual the ``y`` columns hold and ``y0_squares`` sums, a model's (its effects
    predicted on the rows: a nonlinear or per-session model), else the nominal ``y0``; ``terms``: the
    candidate library (else every term of the flight's variables); ``stride`` and ``blocks`` (``K``, else
    :func:`head_blocks`): the selection's sample stride and the first blocks the "after" sums leave
    out. Only the defaults' statistics carry their :func:`library_key` (others are never current when
    stored: the key names no residual, library or stride)."""
    fd = fd if fd is not None else flightdata.flight_data(flight, decoded, spec.vehicle_for(flight))
    vars_ = variables(fd.state, spec.vehicle)
    effects = fx_effects(spec)
    cols = library_columns(terms if terms is not None else library(vars_), effects)
    y = flightdata.targets_of([fd])[0] if residual is None else residual
    k = head_blocks(spec) if blocks is None else blocks
    G, H, H_after = flight_grams(fd, y, cols, effects, spec.vehicle, stride, k)
    after = np.flatnonzero(fd.mask)[fd.blocks() >= k]
    described = tuple((name, tuple(v.unit), tuple(v.sources), v.channel) for name, v in vars_.items())
    plain = residual is None and terms is None and stride == STRIDE and k == head_blocks(spec)
    return FlightLibrary(flight, library_key(spec, flight) if plain else "", source, described, cols.labels(), fd.n,
                         np.asarray(fd.noise, dtype=float), (y[fd.mask] ** 2).sum(axis=0), k, len(after),
                         (y[after] ** 2).sum(axis=0), lambda: (G, H, H_after))


def library_path(root: Any, flight: str) -> Any:
    return sufficient.stats_path(root, flight).parent / "library.bin"


def save(lib: FlightLibrary, root: Any) -> Any:
    """Write a flight's statistics under the data root (atomically); the Gram matrices as their
    upper triangles (``H``: its force and its torque block)."""
    G, H, H_after = lib.grams()
    header = {"format": FORMAT, "flight": lib.flight, "key": lib.key, "source": lib.source,
              "variables": [list(v) for v in lib.variables], "labels": list(lib.labels), "samples": lib.samples,
              "noise": lib.noise.tolist(), "y0_squares": lib.y0_squares.tolist(),  # floats round-trip exactly
              "head_blocks": lib.head_blocks, "samples_after": lib.samples_after,
              "y0_squares_after": lib.y0_squares_after.tolist()}
    force, torque = channel_groups(lib.labels)
    arrays = {"G": sufficient.packed(G)}
    for name, M in (("H", H), ("H_after", H_after)):
        arrays[f"{name}_force"] = sufficient.packed(M[np.ix_(force, force)])
        arrays[f"{name}_torque"] = sufficient.packed(M[np.ix_(torque, torque)])
    return sufficient.write_file(library_path(root, lib.flight), header, arrays)


def load(root: Any, flight: str) -> FlightLibrary:
    """A flight's stored statistics (the header read now, the matrices when asked for);
    :class:`quadcore.identify.stats.sufficient.StatsError` when the file is not one (from :meth:`FlightLibrary.grams`:
    when its matrices are cut short)."""
    path = library_path(root, flight)
    try:
        header, start = sufficient.decode_header(sufficient.read_file(path, header_only=True))
        sufficient.require_format(header, FORMAT)
        labels = tuple(header["labels"])
        arrays = header["arrays"]

        def grams() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            data = sufficient.read_file(path)
            try:
                G, H_force, H_torque, Ha_force, Ha_torque = (
                    sufficient.read_array(data, start, name, arrays[name])
                    for name in ("G", "H_force", "H_torque", "H_after_force", "H_after_torque"))
            except (ValueError, KeyError) as exc:
                raise sufficient.StatsError(f"{path}: {exc}") from None
            return _unpacked(labels, G), _unpacked(labels, H_force, H_torque), _unpacked(labels, Ha_force, Ha_torque)

        variables = tuple((str(n), tuple(u), tuple(s), str(c)) for n, u, s, c in header["variables"])
        return FlightLibrary(header["flight"], header["key"], header["source"], variables, labels,
                             int(header["samples"]), np.array(header["noise"], dtype=float),
                             np.array(header["y0_squares"], dtype=float), int(header["head_blocks"]),
                             int(header["samples_after"]), np.array(header["y0_squares_after"], dtype=float), grams)
    except (ValueError, KeyError, TypeError) as exc:
        raise sufficient.StatsError(f"{path}: not a discovery statistics file ({exc})") from None


@functools.lru_cache(maxsize=4)
def _flat_indices(labels: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    """Where the packed upper triangles go in a flattened (W, W) matrix: ``G``'s, then ``H``'s
    force block and torque block (computed once per layout; a block's columns are in order, so
    its upper triangle lies in the matrix's)."""
    width = len(labels)
    out = []
    for idx in (np.arange(width), *channel_groups(labels)):
        i, j = np.triu_indices(len(idx))
        out.append(idx[i] * width + idx[j])
    return tuple(out)


def _unpacked(labels: tuple[str, ...], *packed: np.ndarray) -> np.ndarray:
    """The symmetric (W, W) matrix of ``G``'s packed triangle, or of ``H``'s two blocks' (zero
    between the blocks): the upper triangle placed, then mirrored (``U + Uᵀ``, the diagonal
    halved back: exact)."""
    width = len(labels)
    where = _flat_indices(labels)
    flat = np.zeros(width * width)
    for P, upper in zip(packed, where[:1] if len(packed) == 1 else where[1:]):
        flat[upper] = P
    U = flat.reshape(width, width)
    M = U + U.T
    M[np.diag_indices(width)] *= 0.5
    return M


def stored(root: Any, spec) -> Callable[[str], FlightLibrary | None]:
    """``flight -> FlightLibrary | None``: a flight's stored statistics if current for ``spec``
    (:func:`library_key`) and made from its decoded table as it is now; None when missing or stale."""
    def current(flight: str) -> FlightLibrary | None:
        lib = sufficient.read_if_present(library_path(root, flight), lambda: load(root, flight))
        if lib is None:
            return None
        fresh = lib.key == library_key(spec, flight) and lib.source == sufficient.decoded_source(root, flight)
        return lib if fresh else None

    return current
