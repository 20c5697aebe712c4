"""The frequency view of the residual (quadcore.identify.describe.spectrum) on a real flight with a gap."""

from __future__ import annotations

import numpy as np
import pytest
from reference import spectra as row_spectra

from quadcore.identify import flightdata
from quadcore.identify.describe import spectrum
from quadcore.logs import flight
from quadcore.physics import vehicle

VEH = vehicle.load()


@pytest.fixture(scope="module")
def long_flight(real_logs):
    return flight.decode_flight(real_logs / "jana01").tables["fixedFrequency"]


def _view(tables: dict) -> dict:
    fds = [flightdata.flight_data(fid, t, VEH) for fid, t in tables.items()]
    return row_spectra.frequency_view(fds, {fd.flight: np.concatenate([fd.r_f, fd.r_tau], axis=1) for fd in fds}, VEH)


def test_a_gap_in_the_log_splits_the_spectra_as_two_flights_would(long_flight):
    """A flight with a 2 s hole has the spectra of its two sides logged as separate flights:
    no Welch segment spans the gap (before, they did, and mixed the two sides' edges)."""
    n = long_flight.height
    before, after = long_flight.slice(0, n // 2), long_flight.slice(n // 2 + 1000)
    assert float(after["t_s"][0] - before["t_s"][-1]) > 1.0  # a real gap, longer than signals.SPLIT_GAP_S
    one = _view({"gapped": long_flight.slice(0, n // 2).vstack(after)})
    two = _view({"before": before, "after": after})
    for a, b in zip(one["channels"], two["channels"]):
        for key in ("residual_rms", "measured_rms", "modelled_rms", "coherence", "gain", "phase_deg"):
            # None (not defined: no model power in a band) as NaN, which must match NaN
            np.testing.assert_allclose(np.array(a[key], dtype=float), np.array(b[key], dtype=float), rtol=1e-9,
                                       atol=1e-15, err_msg=f"{a['channel']} {key}")


def _sums(pp: np.ndarray, mm: np.ndarray, pm: np.ndarray) -> spectrum.SpectrumSums:
    """One flight's spectra as a stored summary gives them (bins 1..K, every channel alike)."""
    sums = spectrum.SpectrumSums(500.0, VEH)
    rr = pp + mm - 2 * pm.real
    spectra = {k: np.repeat(x[:, None], 6, axis=1) for k, x in (("pp", pp), ("mm", mm), ("rr", rr), ("pm", pm))}
    sums.add_spectra(spectra, np.zeros(6), 1000.0, np.zeros(6))
    return sums


def test_a_model_with_no_power_has_no_coherence_gain_or_phase_not_a_huge_one():
    """A stored summary gives the model's spectrum as a quadratic form that is zero up to rounding
    (p = m - r with r = m): a power of ±1e-20 of the measured one and a cross spectrum of rounding.
    Before, the coherence |S_pm|² / max(S_pp S_mm, 1e-300) made that 1e+253 and the gain 7e+276
    (the real-flight report's force x); now the model has no power there, so they are not defined."""
    k = 300
    mm = np.full(k, 1e-6)
    pp = 1e-26 * np.where(np.arange(k) % 2, 1.0, -1.0)  # rounding: either sign
    pm = 1e-22 * (1 + 1j) * np.ones(k)
    view = _sums(pp, mm, pm).view()
    for row in view["channels"]:
        assert row["coherence"] == [None] * len(spectrum.BANDS_HZ), row
        assert row["gain"] == [None] * len(spectrum.BANDS_HZ) and row["modelled_rms"] == [0.0] * 6, row
        assert all(r > 0 for r in row["residual_rms"]), row
    assert all("predicts nothing" in line for line in view["reading"]), view["reading"]


def test_coherence_is_within_its_range_and_out_of_range_is_an_error():
    """A model 0.8 x the measurement, fully coherent: coherence 1 (rounding clipped into [0, 1])
    and gain (measured / modelled) 1.25 in every band; cross spectra that break the Cauchy-Schwarz
    bound (no Welch sum can) raise a typed error instead of reporting a coherence above 1."""
    from quadcore.identify.ranges import StatisticOutOfRange

    k = 300
    mm = np.full(k, 1e-6)
    view = _sums(0.64 * mm, mm, 0.8 * mm + 0j).view()
    for row in view["channels"]:
        assert all(c == pytest.approx(1.0, abs=1e-12) and 0 <= c <= 1 for c in row["coherence"]), row
        assert row["gain"] == pytest.approx([1.25] * 6, rel=1e-12)
    with pytest.raises(StatisticOutOfRange, match="coherence"):
        _sums(0.64 * mm, mm, 1.6 * mm + 0j).view()


def test_a_channel_the_model_predicts_nothing_on_is_n_a_from_rows_and_from_its_summary(long_flight):
    """The nominal model has no horizontal force: force x and y have no coherence, gain or phase
    (None, 'n/a' in the reports), from the rows and from the flight's stored summary alike (its
    model spectrum is there a quadratic form that cancels to rounding: on main it gave 1e+253)."""
    from quadcore.identify.describe import summaries
    from quadcore.identify.stats import sufficient

    fd = flightdata.flight_data("jana01", long_flight, VEH)
    lib = sufficient.library_layout()
    layout = sufficient.Layout(lib.effects, lib.sizes)
    summary = summaries.summarize(fd, VEH, sufficient.design_rows(fd, VEH, layout)).residual(layout.target())
    for view in (_view({"jana01": long_flight}), summaries.frequency_view([summary], summary.fs_hz, VEH)):
        rows = {r["channel"]: r for r in view["channels"]}
        for channel in ("force_x", "force_y"):
            assert rows[channel]["coherence"] == [None] * 6 and rows[channel]["gain"] == [None] * 6, rows[channel]
            assert rows[channel]["modelled_rms"] == [0.0] * 6
        for r in rows.values():
            assert all(c is None or 0 <= c <= 1 for c in r["coherence"]), r
            assert all(g is None or np.isfinite(g) for g in r["gain"]), r
        assert all(c is not None for c in rows["force_z"]["coherence"]), rows["force_z"]
