"""Per-flight summaries of the diagnosis's descriptive part: the residual by regime, by flight, in
time (worst segments) and in frequency (the bins: :mod:`quadcore.identify.describe.regimes`; the bands:
:mod:`quadcore.identify.describe.spectrum`), as quadratic forms of the flight's columns, computed once per
flight and stored beside its statistics (``<root>/stats/flight=<id>/summary.bin``), so that a
diagnosis of a model of linear effects reads no evaluated flight's rows.

**Columns.** Those of :func:`quadcore.identify.stats.sufficient.design_rows`, on every sample:
``z_ic`` (channel ``c``: force x, y, z in N, torque x, y, z in N m, body frame) = the linear
coordinates of every linear effect, then ``y0``. A residual after a model of linear effects is
a signal vector ``v``: ``r_ic = z_ic·v``. Per channel only the columns not identically zero
there are kept (``K_c``, 6 to 10 of the 20 built-in ones; a zero column adds nothing to any
sum), symmetric matrices as their upper triangles.

* **Regimes** (each bin ``k`` of each regime, usable samples): ``n_k`` and
  ``G_kc = Σ_{i∈k} z_ic z_icᵀ``; the bin's sum of squares is ``Σ_i r_ic² = vᵀ G_kc v``. The bins
  of one regime hold every usable sample once: their sum is the flight's (the flight table).
* **Worst segments** (windows ``w = ⌊t / WINDOW_S⌋`` of usable samples): the window's first and
  last time, samples, its most frequent phase, speed and height bin (they do not depend on the
  model; a tie goes to the first in :data:`quadcore.identify.describe.regimes.LABELS` order, where the rows'
  polars ``mode().first()`` picks either), and ``G_wc`` for the force channels:
  ``Σ_{i∈w} |f_res_i|² = Σ_{c<3} vᵀ G_wc v``. A window's Gram is not cheaper than this: the
  ranking needs every window's energy under any ``v``.
* **Spectra** (:class:`quadcore.identify.describe.spectrum.SpectrumSums`): with the measured signal ``m_ic``
  as one more column, ``u = [z_{K_c} | m]``, per gap-free stretch of ``L ≥ 2 SEGMENT`` samples and
  Welch segment ``s`` (Hann window ``h``, each column's mean removed) the FFT ``F_s(f)`` of each
  column, and per frequency bin the cross-spectral matrix (one-sided, unit sample rate)

      C_c(f) = Σ_stretch L · (2 / (N_s Σ h²)) Σ_s conj(F_s(f)) F_s(f)ᵀ       (Hermitian)

  so that any Welch cross spectrum of signals ``a = u·α``, ``b = u·β`` (real vectors) over the
  flight, each stretch weighted by its samples (as the row reference tests/reference/spectra.py
  weights them), is ``αᵀ C β / f_s``: the measurement ``e_m``, the residual ``[v; 0]``, the model
  ``[−v; 1]`` (``p = m − r``). ``S_pp``, ``S_mm``, ``S_rr`` need ``Re C`` only;
  ``S_pm = αᵀ Re C e_m + i αᵀ Im C e_m`` also the column ``Im C[:, m]``. Kept bin by bin up to
  ``MARGIN`` × the top band edge at the flight's own sample rate (the bands and coherence; a fleet whose median rate
  needs more bins takes that flight's rows), with ``Re C`` summed above (the residual's total
  power). The flight's mean residual (reported apart from the spectra) is ``(Σ_i z_ic)·v / n``
  over usable samples.

All are sums over the same samples as the tables made on the rows (the row reference,
tests/reference/tables.py and tests/reference/spectra.py, which tests/test_summaries.py compares
against), in another order: they agree to float rounding (~1e-12 relative).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import polars as pl
from scipy import signal

from quadcore.identify import binfile
from quadcore.identify.describe import regimes, spectrum
from quadcore.identify.describe.regimes import LABELS, REGIMES, RMSE_COLUMNS
from quadcore.physics import residuals, signals
from quadcore.physics.vehicle import Vehicle

if TYPE_CHECKING:
    from quadcore.identify.flightdata import FlightData

FORMAT = 1
FILE_NAME = "summary.bin"
MARGIN = 1.25  # spectral bins kept bin by bin: up to MARGIN × the top band edge at the flight's own rate
BIN_OFFSETS = np.cumsum([0] + [len(LABELS[r]) for r in REGIMES])  # each regime's first bin in the flat list
SEGMENT_LABELS = ("phase", "speed", "height")  # the worst segments' modal labels


@dataclass(frozen=True)
class Packing:
    """Which columns each channel keeps (``cols[c]``, indices into the flight's columns), and
    ``extra`` more columns after them (the measured signal, for the spectra): the upper triangle
    of each channel's ``(k_c + extra)²`` matrix, channel after channel."""

    cols: tuple[np.ndarray, ...]
    extra: int = 0

    def widths(self) -> list[int]:
        return [len(c) + self.extra for c in self.cols]

    def sizes(self) -> list[int]:
        return [k * (k + 1) // 2 for k in self.widths()]

    def pack(self, G: Sequence[np.ndarray]) -> np.ndarray:
        """``G[c]`` (..., k_c, k_c) per channel -> (..., Σ sizes)."""
        return np.concatenate([binfile.packed(g) for g in G], axis=-1)

    def weights(self, a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> np.ndarray:
        """(Σ sizes, channels) such that ``packed @ W`` is ``a_cᵀ G_c b_c`` per channel (``a[c]``,
        ``b[c]``: each channel's vectors over its kept columns): ``a_i b_i`` on the diagonal,
        ``a_i b_j + a_j b_i`` above it."""
        W = np.zeros((sum(self.sizes()[: len(a)]), len(a)))
        start = 0
        for c, (x, y) in enumerate(zip(a, b)):
            i, j = binfile.upper_indices(len(x))
            W[start: start + len(i), c] = np.where(i == j, x[i] * y[j], x[i] * y[j] + x[j] * y[i])
            start += len(i)
        return W


def _channel_columns(Z: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per channel, the columns of ``Z`` (n, 6, W) not identically zero there."""
    nonzero = np.any(Z != 0, axis=0)
    return tuple(np.flatnonzero(nonzero[c]) for c in range(6))


def _group_grams(X: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups, k, k) ``Σ_{i∈g} x_i x_iᵀ`` of the rows ``X`` (n, k) per group (``groups``: each row's)."""
    order = np.argsort(groups, kind="stable")
    edges = np.searchsorted(groups[order], np.arange(n_groups + 1))
    out = np.zeros((n_groups, X.shape[1], X.shape[1]))
    for g, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        if b > a:
            rows = X[order[a:b]]
            out[g] = rows.T @ rows
    return out


def _grams(Z: np.ndarray, packing: Packing, groups: np.ndarray, n_groups: int, channels: range) -> np.ndarray:
    """(n_groups, Σ sizes of ``channels``) the packed per-group Gram of each channel's kept columns."""
    return packing.pack([_group_grams(Z[:, c, packing.cols[c]], groups, n_groups) for c in channels])


def _modes(windows: np.ndarray, n_windows: int, codes: np.ndarray, n_labels: int) -> np.ndarray:
    """Each window's most frequent code (the first in code order when tied)."""
    counts = np.bincount(windows * n_labels + codes, minlength=n_windows * n_labels)
    return counts.reshape(n_windows, n_labels).argmax(axis=1)


def _last_bin_below(hz: float, fs_hz: float) -> int:
    """The last Welch frequency bin below ``hz`` at the sample rate ``fs_hz``: with ``hz`` the top
    band edge, the last one the view reads bin by bin."""
    grid = np.fft.rfftfreq(spectrum.SEGMENT, 1.0 / fs_hz)
    return int(np.flatnonzero(grid < hz)[-1])


def _cross_spectra(U: np.ndarray, stretches: list[slice]) -> np.ndarray:
    """(SEGMENT // 2 + 1, k, k) complex: ``C(f)`` of the module for the columns ``U`` (n, k) over
    the stretches (scipy's Welch: Hann window, half overlap, constant detrend, density, one-sided)."""
    n, half = spectrum.SEGMENT, spectrum.SEGMENT // 2
    window = signal.get_window("hann", n)
    C = np.zeros((half + 1, U.shape[1], U.shape[1]), dtype=complex)
    for part in stretches:
        x = U[part]
        starts = np.arange((len(x) - half) // half) * half
        seg = x[starts[:, None] + np.arange(n)]  # (segments, n, k)
        seg = (seg - seg.mean(axis=1, keepdims=True)) * window[None, :, None]
        F = np.fft.rfft(seg, axis=1).transpose(1, 0, 2)  # (bins, segments, k)
        S = (F.conj().transpose(0, 2, 1) @ F) / (len(starts) * (window ** 2).sum())
        S[1:-1] *= 2  # one-sided: every bin but DC and Nyquist (SEGMENT is even)
        C += (part.stop - part.start) * S
    return C


@dataclass(frozen=True)
class FlightSummary:
    """One flight's summary (see the module) of its first ``width`` columns: the packings of the
    columns (``packing``, and ``spectral`` with the measured signal last), per regime bin the usable samples and packed
    Gram matrices, per window its times, samples, modal labels (codes of ``SEGMENT_LABELS``) and
    the force channels' packed Gram, the column sums over usable samples, and the spectra:
    ``spectrum_re`` (bins 1..K, then the sum above K) and ``spectrum_im`` (bins 1..K) over their
    stretches' ``spectrum_rows`` samples."""

    flight: str
    fs_hz: float
    n: int
    width: int
    packing: Packing
    regime_rows: np.ndarray
    regime_gram: np.ndarray
    window_t_s: np.ndarray
    window_rows: np.ndarray
    window_labels: np.ndarray
    window_gram: np.ndarray
    column_sums: np.ndarray
    spectrum_rows: float
    spectrum_re: np.ndarray
    spectrum_im: np.ndarray

    @property
    def spectral(self) -> Packing:
        return Packing(self.packing.cols, 1)

    def describes(self, v: np.ndarray) -> bool:
        """Whether the signal vector ``v`` lies on the summary's columns (a linear model's residual)."""
        return not np.any(v[self.width:])

    def residual(self, v: np.ndarray) -> ResidualSums:
        """The sums of the residual ``r = z·v`` (``v`` over the flight's columns, :meth:`describes`)."""
        if not self.describes(v):
            raise binfile.StatsError(f"{self.flight}: a signal on columns the summary does not hold")
        P, S = self.packing, self.spectral
        vs = [v[c] for c in P.cols]
        Wv = P.weights(vs, vs)
        bin_ss = self.regime_gram @ Wv
        force_ss = (self.window_gram @ Wv[: self.window_gram.shape[1], :3]).sum(axis=1)
        lin = np.zeros((sum(len(c) for c in P.cols), 6))
        start = 0
        for c, x in enumerate(vs):
            lin[start: start + len(x), c] = x
            start += len(x)
        mean = self.column_sums @ lin / self.n if self.n else np.zeros(6)
        r = [np.append(x, 0.0) for x in vs]
        m = [np.append(np.zeros_like(x), 1.0) for x in vs]
        p = [np.append(-x, 1.0) for x in vs]
        re = self.spectrum_re[:-1]
        spectra = {"pp": re @ S.weights(p, p), "mm": re @ S.weights(m, m), "rr": re @ S.weights(r, r),
                   "pm": re @ S.weights(p, m) - 1j * (self.spectrum_im @ lin)}  # Im of [-v; 1]ᵀ C e_m
        return ResidualSums(self.flight, self.fs_hz, self.regime_rows, bin_ss, self.window_t_s, self.window_rows,
                            self.window_labels, force_ss, spectra, self.spectrum_re[-1] @ S.weights(r, r),
                            self.spectrum_rows, self.spectrum_rows * mean ** 2)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"regime_rows": self.regime_rows, "regime_gram": self.regime_gram, "window_t_s": self.window_t_s,
                "window_rows": self.window_rows, "window_labels": self.window_labels,
                "window_gram": self.window_gram, "column_sums": self.column_sums,
                "spectrum_re": self.spectrum_re, "spectrum_im": self.spectrum_im}


@dataclass(frozen=True)
class ResidualSums:
    """One flight's sums of one residual: per regime bin the samples and the sum of squares per
    channel (N_bins, 6); per window its times, samples, modal labels and force sum of squares;
    its spectra at bins 1..K as :meth:`quadcore.identify.describe.spectrum.SpectrumSums.add_spectra` takes
    them."""

    flight: str
    fs_hz: float
    bin_rows: np.ndarray
    bin_ss: np.ndarray
    window_t_s: np.ndarray
    window_rows: np.ndarray
    window_labels: np.ndarray
    window_force_ss: np.ndarray
    spectra: dict[str, np.ndarray]
    rr_above: np.ndarray
    spectrum_rows: float
    mean_sq: np.ndarray

    @property
    def n(self) -> int:
        return int(self.bin_rows[: BIN_OFFSETS[1]].sum())

    def covers(self, fs_hz: float) -> bool:
        """Whether the bins kept one by one are every bin the view reads at the fleet's rate ``fs_hz``."""
        return not self.spectrum_rows or len(self.spectra["rr"]) >= _last_bin_below(spectrum.BANDS_HZ[-1][1], fs_hz)

    @property
    def ss(self) -> np.ndarray:
        """(6,) the flight's sum of squares (over the bins of the first regime: every sample once)."""
        return self.bin_ss[: BIN_OFFSETS[1]].sum(axis=0)


def summarize(fd: FlightData, vehicle: Vehicle, Z: np.ndarray, top_bin: int | None = None) -> FlightSummary:
    """A flight's summary from its rows: ``fd`` a :class:`quadcore.identify.flightdata.FlightData`,
    ``Z`` (n, 6, W) its columns on every sample, ``vehicle`` the model's (thrust-to-weight, the
    measured signal). ``top_bin``: the last spectral bin kept one by one (default: from
    ``MARGIN`` at the flight's rate)."""
    packing = Packing(_channel_columns(Z))
    Zm = Z[fd.mask]
    codes = {k: c[fd.mask] for k, c in regimes.regime_codes(regimes.regime_columns(fd, vehicle)).items()}
    fs_hz = float(spectrum.sample_rate_hz(fd.state.t_s))
    K = min(_last_bin_below(MARGIN * spectrum.BANDS_HZ[-1][1], fs_hz) if top_bin is None else top_bin,
            spectrum.SEGMENT // 2)
    regime_rows, regime_gram = _regime_sums(Zm, packing, codes)
    window_t_s, window_rows, window_labels, window_gram = _window_sums(Zm, packing, codes, fd.state.t_s[fd.mask])
    spectrum_rows, spectrum_re, spectrum_im = _spectral_sums(fd, vehicle, Z, packing, K)
    return FlightSummary(fd.flight, fs_hz, len(Zm), Z.shape[2], packing, regime_rows, regime_gram,
                         window_t_s, window_rows, window_labels, window_gram,
                         np.concatenate([Zm[:, c, packing.cols[c]].sum(axis=0) for c in range(6)]),
                         spectrum_rows, spectrum_re, spectrum_im)


def _regime_sums(Zm: np.ndarray, packing: Packing, codes: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per bin of every regime (usable samples ``Zm``, their bins ``codes``): samples, packed Gram."""
    rows = np.concatenate([np.bincount(codes[r], minlength=len(LABELS[r])) for r in REGIMES])
    return rows, np.concatenate([_grams(Zm, packing, codes[r], len(LABELS[r]), range(6)) for r in REGIMES])


def _window_sums(Zm: np.ndarray, packing: Packing, codes: dict[str, np.ndarray],
                 t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per window (usable samples at ``t_s``, grouped as the row reference's ``worst_segments``
    in tests/reference/tables.py groups the rows): first and last time, samples, modal labels, the
    force channels' packed Gram."""
    _, window = np.unique(t_s // regimes.WINDOW_S, return_inverse=True)
    window = window.reshape(-1)
    n_w = int(window.max()) + 1 if len(window) else 0
    t_first, t_last = np.full(n_w, np.inf), np.full(n_w, -np.inf)
    np.minimum.at(t_first, window, t_s)
    np.maximum.at(t_last, window, t_s)
    labels = np.stack([_modes(window, n_w, codes[k], len(LABELS[k])) for k in SEGMENT_LABELS], axis=1)
    return (np.stack([t_first, t_last], axis=1), np.bincount(window, minlength=n_w), labels,
            _grams(Zm, packing, window, n_w, range(3)))


def _spectral_sums(fd: FlightData, vehicle: Vehicle, Z: np.ndarray, packing: Packing,
                   K: int) -> tuple[float, np.ndarray, np.ndarray]:
    """The stretches' samples, ``Re C`` packed at bins 1..K and summed above K, and ``Im C[:, m]`` at bins 1..K."""
    stretches = [p for p in signals.segments(fd.state.t_s) if p.stop - p.start >= 2 * spectrum.SEGMENT]
    meas = np.concatenate(residuals.measured_wrench(fd.state, vehicle), axis=1)
    C = [_cross_spectra(np.concatenate([Z[:, c, packing.cols[c]], meas[:, c:c + 1]], axis=1), stretches)
         for c in range(6)]
    re = [np.concatenate([c.real[1: K + 1], c.real[K + 1:].sum(axis=0, keepdims=True)]) for c in C]
    return (float(sum(p.stop - p.start for p in stretches)), Packing(packing.cols, 1).pack(re),
            np.concatenate([c.imag[1: K + 1, :-1, -1] for c in C], axis=1))


def of_rows(fd: FlightData, residual_rows: np.ndarray, vehicle: Vehicle) -> FlightSummary:
    """The summary of one residual given as rows (n, 6): its only column, every spectral bin kept."""
    return summarize(fd, vehicle, residual_rows[:, :, None], top_bin=spectrum.SEGMENT // 2)


# ---------------------------------------------------------------------------------------
# The tables, from the flights' sums (as tests/reference/tables.py makes them from rows)
# ---------------------------------------------------------------------------------------

def _rmse_columns(ss: np.ndarray, rows: np.ndarray) -> dict[str, np.ndarray]:
    ss = np.maximum(ss, 0.0)  # a quadratic form of the summaries: >= 0 but for rounding
    return {name: np.sqrt(ss[:, j] / rows) for j, name in enumerate(RMSE_COLUMNS)}


def regime_table(sums: Sequence[ResidualSums]) -> pl.DataFrame:
    """Residual RMSE per axis in every bin of every regime variable, and the share of samples, of the
    flights' sums (the row reference: ``regime_table`` in tests/reference/tables.py)."""
    rows = np.sum([s.bin_rows for s in sums], axis=0)
    ss = np.sum([s.bin_ss for s in sums], axis=0)
    total = int(rows[: BIN_OFFSETS[1]].sum())
    frames = []
    for r, regime in enumerate(REGIMES):
        sl = slice(BIN_OFFSETS[r], BIN_OFFSETS[r + 1])
        seen = rows[sl] > 0
        frame = pl.DataFrame({"regime": regime, "bin": np.asarray(LABELS[regime])[seen],
                              "samples": rows[sl][seen].astype(np.uint32),
                              **_rmse_columns(ss[sl][seen], rows[sl][seen])})
        frames.append(frame.sort("bin"))
    return pl.concat(frames).with_columns((pl.col("samples") / total).alias("share"))


def flight_table(sums: Sequence[ResidualSums]) -> pl.DataFrame:
    """Residual RMSE per axis of each flight, and its samples, of the flights' sums (the row
    reference: ``flight_table`` in tests/reference/tables.py)."""
    rows = np.array([s.n for s in sums])
    return pl.DataFrame({"flight": [s.flight for s in sums], "samples": rows.astype(np.uint32),
                         **_rmse_columns(np.stack([s.ss for s in sums]), rows)}).sort("flight")


def worst_segments(sums: Sequence[ResidualSums], top: int = regimes.TOP_SEGMENTS) -> pl.DataFrame:
    """The ``top`` windows (non-overlapping, per flight) with the largest force-residual RMS, of the
    flights' sums (the row reference: ``worst_segments`` in tests/reference/tables.py)."""
    frame = {"flight": np.concatenate([np.full(len(s.window_rows), s.flight) for s in sums]),
             "t_start_s": np.concatenate([s.window_t_s[:, 0] for s in sums]),
             "t_end_s": np.concatenate([s.window_t_s[:, 1] for s in sums]),
             "force_rms_N": np.sqrt(np.concatenate([s.window_force_ss / s.window_rows for s in sums]))}
    codes = np.concatenate([s.window_labels for s in sums])
    for k, name in enumerate(SEGMENT_LABELS):
        frame[name] = np.asarray(LABELS[name])[codes[:, k]]
    return pl.DataFrame(frame).sort("force_rms_N", descending=True).head(top)


def frequency_view(sums: Sequence[ResidualSums], fs_hz: float, vehicle: Vehicle) -> dict:
    """The residual by frequency band and the coherence of model and measurement (JSON-ready,
    :mod:`quadcore.identify.describe.spectrum`) of the flights' sums, at the fleet's rate ``fs_hz`` (the row
    reference: ``frequency_view`` in tests/reference/spectra.py)."""
    acc = spectrum.SpectrumSums(fs_hz, vehicle)
    for s in sums:
        if s.spectrum_rows:
            acc.add_spectra(s.spectra, s.rr_above, s.spectrum_rows, s.mean_sq)
    return acc.view()


@dataclass(frozen=True)
class Tables:
    """The evaluated flights' residual by regime, by flight, in time and in frequency."""

    regimes: pl.DataFrame
    flights: pl.DataFrame
    worst_segments: pl.DataFrame
    frequency: dict


def tables(sums: list[ResidualSums], redo: Callable[[str], ResidualSums], vehicle: Vehicle) -> Tables:
    """The tables of the flights' sums, the spectra at the fleet's median sample rate;
    ``redo(flight)``: a flight's sums with every spectral bin (from its rows), for one whose
    summary keeps too few bins for that rate."""
    fs_hz = float(np.median([s.fs_hz for s in sums]))
    sums = [s if s.covers(fs_hz) else redo(s.flight) for s in sums]
    return Tables(regime_table(sums), flight_table(sums), worst_segments(sums), frequency_view(sums, fs_hz, vehicle))


# ---------------------------------------------------------------------------------------
# Storage, beside the flight's statistics
# ---------------------------------------------------------------------------------------

def path(root: Any, flight: str) -> Any:
    return binfile.stats_path(root, flight).parent / FILE_NAME


def save(summary: FlightSummary, root: Any, key: str, source: str) -> Any:
    """Write a flight's summary under the data root (atomically), for the statistics ``key`` made
    from the decoded table of the log ``source``."""
    header = {"flight": summary.flight, "key": key, "source": source, "format": FORMAT, "fs_hz": summary.fs_hz,
              "n": summary.n, "width": summary.width, "cols": [c.tolist() for c in summary.packing.cols],
              "spectrum_rows": summary.spectrum_rows}
    return binfile.write_file(path(root, summary.flight), header, summary.arrays())


def load(root: Any, flight: str, key: str, source: str) -> FlightSummary | None:
    """A flight's stored summary if it was made for the statistics ``key`` from the log
    ``source``; None when missing, stale or not a summary file."""
    p = path(root, flight)
    if not p.exists():
        return None
    raw = binfile.read_file(p)
    try:
        header, array = binfile.decode(raw)
        if (header.get("format"), header.get("key"), header.get("source")) != (FORMAT, key, source):
            return None
        packing = Packing(tuple(np.asarray(c, dtype=int) for c in header["cols"]))
        return FlightSummary(flight, float(header["fs_hz"]), int(header["n"]), int(header["width"]), packing,
                             array("regime_rows"),
                             array("regime_gram"), array("window_t_s"), array("window_rows"), array("window_labels"),
                             array("window_gram"), array("column_sums"), float(header["spectrum_rows"]),
                             array("spectrum_re"), array("spectrum_im"))
    except (ValueError, KeyError, TypeError):
        return None
