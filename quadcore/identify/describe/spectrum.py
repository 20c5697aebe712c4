"""Where the model fails, in frequency: the residual's power by band, and how the modelled
force and torque relate to the measured ones band by band.

For each body-frame channel (force x, y, z; torque x, y, z), on the evaluated flights,
Welch spectra (Hann windows of ``SEGMENT`` samples, half overlap) of the measured signal
``m`` (``m sf_b`` / ``J dω/dt + ω × Jω``), the modelled one ``p`` (thrust map + effects,
through the same filters) and the residual ``r = m - p`` are averaged over flights
(weighted by their samples; each stretch between gaps in the log is a signal of its own,
so no Welch segment spans a gap). Per band:

* ``residual_rms``: ``sqrt(∫ S_rr df)`` over the band, and ``residual_share`` the share of
  the residual's mean square that lies there. Each segment's mean is removed before the
  spectra, so a constant offset per flight (a trim, a bias) is reported apart:
  ``residual_mean_rms`` (RMS over flights of each flight's mean residual) and ``mean_share``;
  band shares and mean share add up to about 1;
* ``coherence``: ``|S_pm|² / (S_pp S_mm)``, averaged over the band's bins: 1 where the
  measurement is a linear, time-invariant function of the model, 0 where they are unrelated;
* ``gain`` and ``phase_deg``: the transfer from modelled to measured,
  ``H = Σ S_pm / Σ S_pp`` over the band: a gain below 1 with a phase near 0 is a mis-scaled
  model; a phase lag growing with frequency is timing (a lag or a delay between the logged
  inputs and the force).

How to read it (``reading``): residual power in a band with high coherence is the model's
own signal, mis-scaled or mistimed there (fix the map or the timing); residual power in a
band with low coherence is something the model's inputs do not carry: slow physics or an
offset below ~0.5 Hz, input or sensor noise at high frequency.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadcore.identify import ranges
from quadcore.physics.dynamics import XYZ

BANDS_HZ = ((0.0, 0.5), (0.5, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 50.0))
SEGMENT = 1024  # samples per Welch segment (about 2 s at 500 Hz: 0.5 Hz resolution)
RESOLVED = 1e-9  # a band's (a bin's) power below this share of its model + measured + residual power is 0
CHECKED = 1e-6  # a bin's coherence is range-checked where model and measured power exceed this share of its total
COHERENT = 0.7  # band coherence above which the residual there is the model's own signal, mis-scaled or late
CHANNELS = tuple([f"force_{a}" for a in XYZ] + [f"torque_{a}" for a in XYZ])
BAND_KEYS = ("residual_rms", "measured_rms", "modelled_rms", "coherence", "gain", "phase_deg")  # a list per channel


def sample_rate_hz(t_s: np.ndarray) -> float:
    """A flight's sample rate: 1 / the median interval between samples."""
    return 1.0 / np.median(np.diff(t_s))


class SpectrumSums:
    """The evaluated flights' spectra, summed flight by flight (:meth:`add_spectra`, from each
    flight's stored summary) on a common frequency grid, and the view of them (:meth:`view`);
    ``fs_hz``: the evaluated flights' median :func:`sample_rate_hz`. The same sums computed on a
    flight's rows with ``scipy.signal.welch``, the reference they are tested against:
    tests/reference/spectra.py."""

    def __init__(self, fs_hz: float, vehicle):
        self.fs, self.vehicle = fs_hz, vehicle
        self.grid = np.fft.rfftfreq(SEGMENT, 1.0 / fs_hz)
        self.acc = {k: np.zeros((len(self.grid), 6), dtype=complex if k == "pm" else float)
                    for k in ("pp", "mm", "rr", "pm")}
        self.weight = 0.0
        self.mean_sq = np.zeros(6)  # per-flight mean of the residual, squared (what no spectrum shows)
        self.rr_above = np.zeros(6)  # residual power of bins added as a sum, not bin by bin

    def add_spectra(self, spectra: dict[str, np.ndarray], rr_above: np.ndarray, weight: float,
                    mean_sq: np.ndarray) -> None:
        """One flight's sums (from its stored summary, :mod:`quadcore.identify.describe.summaries`):
        ``spectra[key]`` (K, 6) its stretches' spectra at bins 1..K, weighted by their samples,
        with a unit sample rate (divided by ``fs_hz`` here);
        ``rr_above`` (6,) the residual's above bin K summed; ``weight`` its stretches' samples;
        ``mean_sq`` (6,) ``weight`` × its mean residual squared."""
        for key, s in spectra.items():
            self.acc[key][1: 1 + len(s)] += s / self.fs
        self.rr_above += rr_above / self.fs
        self.mean_sq += mean_sq
        self.weight += weight

    def view(self) -> dict:
        """The JSON-ready view of the flights added so far."""
        return _view(self.fs, self.grid, self.acc, self.weight, self.mean_sq, self.rr_above)


def _view(fs: float, grid: np.ndarray, acc: dict, weight: float, mean_sq: np.ndarray, rr_above: np.ndarray) -> dict:
    """The bands, coherence and readings from the sample-weighted sums of the spectra."""
    if weight == 0:
        return {"bands_hz": [list(b) for b in BANDS_HZ], "channels": [], "reading": ["flights too short for spectra"]}
    s = {k: v / weight for k, v in acc.items()}
    mean_sq = mean_sq / weight
    rr_above = rr_above / weight
    df = grid[1] - grid[0]
    rows = []
    for c, name in enumerate(CHANNELS):
        row: dict[str, Any] = {"channel": name, "unit": "N" if c < 3 else "N m", "residual_rms": [], "measured_rms": [],
               "modelled_rms": [], "coherence": [], "gain": [], "phase_deg": []}
        total = float((s["rr"][1:, c].sum() + rr_above[c]) * df + mean_sq[c])
        shares = []
        for lo, hi in BANDS_HZ:
            band = _band_view(s, (grid >= lo) & (grid < hi) & (grid > 0), c, df, f"{name} at {lo:g}-{hi:g} Hz")
            for key in BAND_KEYS:
                row[key].append(band[key])
            shares.append(band["residual_power"] / total if total > 0 else 0.0)
        row["residual_share"] = shares
        row["residual_mean_rms"] = float(np.sqrt(mean_sq[c]))
        row["mean_share"] = float(mean_sq[c] / total) if total > 0 else 0.0
        rows.append(row)
    return {"bands_hz": [list(b) for b in BANDS_HZ], "sample_rate_hz": fs, "segment_samples": SEGMENT,
            "channels": rows, "reading": [reading(r) for r in rows]}


def _resolved(power: np.ndarray, total: np.ndarray) -> np.ndarray:
    """``power`` where it exceeds ``RESOLVED`` × ``total``, else 0 (zero within the sums' rounding)."""
    return np.where(power > RESOLVED * total, power, 0.0)


def _band_view(s: dict, b: np.ndarray, c: int, df: float, where: str) -> dict[str, Any]:
    """One band (bins ``b``, ``df`` apart) of channel ``c``: the RMS of the residual, the
    measurement and the model, the residual's power, the coherence (the mean over the bins where
    both model and measurement have power) and the transfer from model to measurement. A band
    with no bins (above the Nyquist frequency) has nothing defined (None); a band where the model
    or the measurement has no power has no coherence, gain or phase (None): 0 / 0 there."""
    if not b.any():
        return dict.fromkeys(BAND_KEYS) | {"residual_power": 0.0}
    pp, mm, rr, pm = (s[k][b, c] for k in ("pp", "mm", "rr", "pm"))
    bin_total = pp + mm + rr
    pp, mm, rr = (_resolved(x, bin_total) for x in (pp, mm, rr))
    band_pp, band_mm, band_rr = (float(_resolved(x.sum(), bin_total.sum())) for x in (pp, mm, rr))
    out: dict[str, Any] = {"residual_rms": float(np.sqrt(band_rr * df)), "measured_rms": float(np.sqrt(band_mm * df)),
                           "modelled_rms": float(np.sqrt(band_pp * df)), "residual_power": band_rr * df,
                           "coherence": None, "gain": None, "phase_deg": None}
    both = (pp > 0) & (mm > 0)
    if band_pp > 0 and band_mm > 0 and both.any():
        per_bin = np.abs(pm[both]) ** 2 / (pp[both] * mm[both])
        sure = np.minimum(pp[both], mm[both]) > CHECKED * bin_total[both]
        if sure.any():  # where both powers are well above the sums' rounding, above 1 is a defect
            ranges.unit_fraction(float(per_bin[sure].max()), f"the coherence of {where} (its largest bin)")
        per_bin = np.clip(per_bin, 0.0, 1.0)  # elsewhere rounding of a power near RESOLVED may carry it past 1
        out["coherence"] = ranges.unit_fraction(float(per_bin.mean()), f"the coherence of {where}")
        h = pm.sum() / band_pp
        out["gain"] = ranges.finite(np.abs(h), f"the gain of {where}")
        out["phase_deg"] = ranges.finite(np.degrees(np.angle(h)), f"the phase of {where}")
    return out


def _mismatched(row: dict, i: int) -> bool:
    """The transfer from model to measurement in band ``i`` is not ~1 (gain within 15 %, phase within 15°)."""
    return abs(row["gain"][i] - 1) > 0.15 or abs(row["phase_deg"][i]) > 15


def _band(i: int) -> str:
    lo, hi = BANDS_HZ[i]
    return f"{lo:g}-{hi:g} Hz"


def reading(row: dict) -> str:
    """One sentence per channel: where its residual lies and what that band says."""
    shares = np.asarray(row["residual_share"])
    top = int(np.argmax(shares))
    coherent = [i for i, c in enumerate(row["coherence"])
                if c is not None and c >= COHERENT and shares[i] >= 0.1 and _mismatched(row, i)]
    if row["mean_share"] >= shares[top]:
        text = (f"{row['channel']}: {row['mean_share']:.0%} of the residual power is a constant offset per flight "
                f"(RMS of the flights' means {row['residual_mean_rms']:.3g} {row['unit']}): a trim or bias that "
                f"changes between flights (a centre of mass, a thrust map, a sensor bias); the largest band is "
                f"{_band(top)} ({shares[top]:.0%})")
        others = [i for i in coherent]
        if others:
            text += "; coherent but mismatched at " + ", ".join(
                f"{_band(i)} ({shares[i]:.0%}: gain {row['gain'][i]:.2f}, {row['phase_deg'][i]:+.0f}°)" for i in others)
        return text + "."
    text = f"{row['channel']}: {shares[top]:.0%} of the residual power is at {_band(top)}"
    c = row["coherence"][top]
    if not any(row["modelled_rms"]):  # None (no bins) or 0 (no power) in every band
        return text + ": the model predicts nothing on this axis, so the residual is the measurement itself."
    if c is None:
        text += ": the model predicts nothing in this band, so the residual there is the measurement itself"
    elif c >= COHERENT and not _mismatched(row, top):
        text += (f", where model and measurement are coherent ({c:.2f}) and agree (gain {row['gain'][top]:.2f}, "
                 f"{row['phase_deg'][top]:+.0f}°): what is left there is the incoherent part (noise, or what the "
                 "inputs do not carry)")
    elif c >= COHERENT:
        text += (f", where model and measurement are coherent ({c:.2f}) but the measurement is "
                 f"{row['gain'][top]:.2f} × the model at {row['phase_deg'][top]:+.0f}°: the model's own signal, "
                 + ("late or early (timing: a lag or delay)" if abs(row["phase_deg"][top]) > 20 else "mis-scaled"))
    elif BANDS_HZ[top][1] <= 0.5:
        text += (f", where model and measurement are not coherent ({c:.2f}): a slow offset or drift the model's "
                 "inputs do not carry (slow physics, a per-flight trim or bias)")
    else:
        text += (f", where model and measurement are not coherent ({c:.2f}): something the model's inputs do "
                 "not carry (unmodelled physics, or input / sensor noise)")
    others = [i for i in coherent if i != top]
    if others:
        text += "; coherent but mismatched also at " + ", ".join(
            f"{_band(i)} ({shares[i]:.0%}: gain {row['gain'][i]:.2f}, {row['phase_deg'][i]:+.0f}°)" for i in others)
    return text + "."
