"""Per-flight summaries of the diagnosis's descriptive part: the regime table, the flight table,
the worst segments and the frequency view from a flight's stored summary equal those from its
rows (the same sums in another order), on simulated and real flights; and a diagnosis of a
model of linear effects on stored statistics reads no evaluated flight's rows."""

from __future__ import annotations

import gc
import math
import weakref

import numpy as np
import polars as pl
import pytest
from reference import spectra as row_spectra, tables as row_tables

from quadcore import effects
from quadcore.identify import diagnosis, flightdata, rates
from quadcore.identify.describe import summaries
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.spec.model import spec_from

VEHICLE = vehicle.load()
REL = 1e-9
# The library's effects, not every effect this process has loaded: a plugin another test loaded is
# a candidate only its model file offers, and its statistics are computed from rows by design
# (sufficient.spec_layout)
LINEAR = [n for n in effects.builtin_names() if effects.get(n).linear]


def _close(a, b, where: str = "") -> None:
    """JSON-like values equal: text, counts and structure exactly, floats to ``REL``."""
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and not isinstance(b, bool):
        # a phase is an angle: near 0° (a real transfer) it is rounding, in degrees, not relative;
        # an explained share is a fraction of the residual: near 0 (an effect that explains nothing)
        # its rounding is that of 1, not relative to its own size
        tiny = 1e-9 if "phase_deg" in where else 1e-12 if "explained" in where or "share" in where else 1e-300
        assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=REL, abs=tiny), f"{where}: {a} vs {b}"
    else:
        assert a == b, f"{where}: {a!r} vs {b!r}"


def _same_array(a: np.ndarray, b: np.ndarray, name: str) -> None:
    """Equal arrays: integers exactly, floats to ``REL`` of the array's largest value (the same
    sums computed from another allocation may round differently: never compare them bit for bit)."""
    assert a.dtype == b.dtype and a.shape == b.shape, name
    if a.dtype.kind == "f" or a.dtype.kind == "c":
        np.testing.assert_allclose(a, b, rtol=REL, atol=REL * float(np.abs(b).max(initial=0.0)), err_msg=name)
    else:
        np.testing.assert_array_equal(a, b, err_msg=name)


def _same_file(a, b) -> None:
    """Two files of :func:`quadcore.identify.stats.sufficient.encode`: the same header, the same arrays
    (:func:`_same_array`)."""
    (head_a, array_a), (head_b, array_b) = (sufficient.decode(p.read_bytes()) for p in (a, b))
    assert head_a == head_b, a.name
    for name in head_a["arrays"]:
        _same_array(array_a(name), array_b(name), f"{a.name}: {name}")


def _same_frame(a: pl.DataFrame, b: pl.DataFrame) -> None:
    assert a.schema == b.schema
    _close(a.to_dicts(), b.to_dicts())


def _layout() -> sufficient.Layout:
    """Every linear effect's columns and y0 (what a summary holds), without the profiles' extras."""
    lib = sufficient.library_layout()
    return sufficient.Layout(lib.effects, lib.sizes)


def _residual(layout: sufficient.Layout) -> np.ndarray:
    """A residual after a model of three linear effects, as a signal vector."""
    v = layout.target()
    v[layout.cols("rotor_drag")] = [-0.1, -0.12, -0.05]
    v[layout.cols("thrust_scale")] = [-0.05]
    v[layout.cols("com_offset")] = [1e-3, -2e-3]
    return v


def _compare(tables: dict) -> None:
    """The tables of each flight's summary against the rows' on ``tables`` (flight -> decoded table)."""
    layout = _layout()
    fds = {f: flightdata.flight_data(f, t, VEHICLE) for f, t in tables.items()}
    for v in (layout.target(), _residual(layout)):  # the nominal residual, and one after a fit
        rows = {f: sufficient.signal_rows(fd, VEHICLE, layout, v) for f, fd in fds.items()}
        long = row_tables.long_table(list(fds.values()), rows, VEHICLE)
        sums = [summaries.summarize(fd, VEHICLE, sufficient.design_rows(fd, VEHICLE, layout)).residual(v)
                for fd in fds.values()]

        def never(f):
            raise AssertionError(f"{f}'s summary keeps too few spectral bins")

        got = summaries.tables(sums, never, VEHICLE)
        _same_frame(got.regimes, row_tables.regime_table(long))
        _same_frame(got.flights, row_tables.flight_table(long))
        _same_frame(got.worst_segments, row_tables.worst_segments(long))
        _close(got.frequency, row_spectra.frequency_view(list(fds.values()), rows, VEHICLE))


def test_tables_from_summaries_equal_the_rows_on_simulated_flights(drag_fleet):
    tables = {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(drag_fleet)}
    _compare(tables)


def test_tables_from_summaries_equal_the_rows_on_real_flights(real_logs):
    tables = {name: flight.decode_flight(real_logs / name).tables["fixedFrequency"]
              for name in ("jana02", "jana05", "jana20")}  # two sessions, one with a stuck voltage log
    _compare(tables)


def test_a_residual_given_as_rows_summarises_alike(drag_fleet):
    """A residual that is no combination of columns (a nonlinear model's) as its own column."""
    p = flight.discover_logs(drag_fleet)[0]
    fd = flightdata.flight_data(p.name, flight.decode_flight(p).tables["fixedFrequency"], VEHICLE)
    r = sufficient.signal_rows(fd, VEHICLE, _layout(), _residual(_layout()))
    got = summaries.tables([summaries.of_rows(fd, r, VEHICLE).residual(np.ones(1))], None, VEHICLE)
    long = row_tables.long_table([fd], {fd.flight: r}, VEHICLE)
    _same_frame(got.regimes, row_tables.regime_table(long))
    _close(got.frequency, row_spectra.frequency_view([fd], {fd.flight: r}, VEHICLE))


def test_a_summary_with_too_few_spectral_bins_for_the_fleet_takes_its_rows(drag_fleet):
    """A flight whose summary stops below the bins the fleet's sample rate needs (a fast log among
    slow ones) is described from its rows, to the same view."""
    p = flight.discover_logs(drag_fleet)[0]
    fd = flightdata.flight_data(p.name, flight.decode_flight(p).tables["fixedFrequency"], VEHICLE)
    layout = _layout()
    v = _residual(layout)
    short = summaries.summarize(fd, VEHICLE, sufficient.design_rows(fd, VEHICLE, layout), top_bin=40).residual(v)
    redone = []

    def from_rows(f):
        redone.append(f)
        return summaries.of_rows(fd, sufficient.signal_rows(fd, VEHICLE, layout, v), VEHICLE).residual(np.ones(1))

    got = summaries.tables([short], from_rows, VEHICLE)
    assert redone == [fd.flight]
    rows = {fd.flight: sufficient.signal_rows(fd, VEHICLE, layout, v)}
    _close(got.frequency, row_spectra.frequency_view([fd], rows, VEHICLE))


@pytest.fixture(scope="module")
def stored_root(drag_fleet, tmp_path_factory):
    """The shared fleet's statistics as the per-flight asset stores them, for a model of rotor drag."""
    root = tmp_path_factory.mktemp("summaries_root")
    spec = spec_from(VEHICLE, ["rotor_drag"])
    tables = {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(drag_fleet)}
    for f, t in tables.items():
        sufficient.save(sufficient.compute_current(spec, f, t, source=f"log-of-{f}"), root)
    return root, spec, tables


def test_summaries_are_stored_beside_the_statistics_and_follow_them(stored_root):
    root, spec, tables = stored_root
    f = sorted(tables)[0]
    s = sufficient.load(root, f)
    summary = s.summary()
    assert summaries.path(root, f).is_file() and summary is not None
    made = sufficient.compute_current(spec, f, tables[f], source=f"log-of-{f}").summary()
    for name, a in made.arrays().items():
        _same_array(getattr(summary, name), a, name)
    # another key or another log: stale, so the flight is described from its rows
    assert summaries.load(root, f, "another-key", s.source) is None
    assert summaries.load(root, f, s.key, "another-log") is None
    # a summary file cut short is no summary, not a crash
    cut = summaries.path(root, "cut")
    cut.parent.mkdir(parents=True)
    cut.write_bytes(summaries.path(root, f).read_bytes()[:5000])
    assert summaries.load(root, "cut", s.key, s.source) is None


def _timing_reads_rows(judge, tables: dict, held: list[int]):
    """``rates.judge`` given the flights' rows (read from ``tables``), whatever it is handed;
    ``held`` gets, at each read, how many flights' rows read before are still alive."""

    def with_rows(rows, cands, rows_of, *args, **kwargs):
        refs: list[weakref.ref] = []

        def alive() -> int:
            gc.collect()
            return sum(r() is not None for r in refs)

        def own_rows(f: str):
            held.append(alive())
            fd = flightdata.flight_data(f, tables[f], VEHICLE)
            refs.append(weakref.ref(fd))
            return fd

        out = judge(rows, cands, own_rows, *args, **kwargs)
        held.append(alive())
        return out

    return with_rows


class _NoRows(dict):
    """Decoded tables whose rows may not be read."""

    def __init__(self, tables: dict):
        super().__init__({f: None for f in tables})

    def __getitem__(self, f):
        raise AssertionError(f"{f}'s rows were read")


@pytest.mark.parametrize("holdout", [None, ["sim003"]])
def test_a_diagnosis_on_stored_statistics_reads_no_rows_and_equals_the_rows(stored_root, holdout):
    """Cross-validation (every flight evaluated) and a held-out flight: model, candidates, tests,
    and the regime, flight, segment and frequency tables from the stored statistics and
    summaries, not one row read; the same document as from the rows."""
    root, spec, tables = stored_root
    linear = [n for n in LINEAR if n not in spec.effects]
    stored = diagnosis.diagnose(_NoRows(tables), spec, holdout, linear, stats=lambda f: sufficient.load(root, f))
    from_rows = diagnosis.diagnose(tables, spec, holdout, linear)
    _close(stored.to_dict(), from_rows.to_dict())


def test_with_every_candidate_the_evaluated_flights_tables_come_from_their_summaries(stored_root):
    """The library's candidates, the one-parameter nonlinear ones too: the evaluated flights'
    tables and spectra still come from their summaries, equal to the rows'. The timing candidates'
    rate level reads each flight's rows once (it is not in the stored statistics: docs/timing.md),
    and only it (without a timing candidate nothing reads a row), one flight at a time: each
    flight's rows are reduced to its rate-level sums and let go before the next is read, and none
    is held after it."""
    root, spec, tables = stored_root
    library = [n for n in effects.builtin_names() if n not in spec.effects and effects.get(n).offered]
    untimed = [n for n in library if not effects.get(n).retimes_thrust]
    assert untimed != library
    diagnosis.diagnose(_NoRows(tables), spec, candidates=untimed, stats=lambda f: sufficient.load(root, f))
    held: list[int] = []
    with pytest.MonkeyPatch.context() as m:
        m.setattr(rates, "judge", _timing_reads_rows(rates.judge, tables, held))
        stored = diagnosis.diagnose(_NoRows(tables), spec, candidates=library,
                                    stats=lambda f: sufficient.load(root, f)).to_dict()
    assert len(held) == len(tables) + 1 and not any(held), held  # every flight read once, none held
    from_rows = diagnosis.diagnose(tables, spec, candidates=library).to_dict()
    for key in ("regimes", "flights", "worst_segments", "frequency", "baseline"):
        _close(stored[key], from_rows[key], key)


def test_one_flight_data_for_all_three_stores_the_same_files(stored_root, tmp_path):
    """The statistics asset builds a flight's FlightData once and passes it to the sufficient
    statistics, the summary and the library statistics (the bases cached by the first reused by
    the others): the stored files are those of each computed on its own (the same headers, the
    same arrays to rounding), the summary that of the design built afresh (the previous code's way)."""
    from quadcore.identify.discovery import library_stats

    _, spec, tables = stored_root
    f = sorted(tables)[0]
    shared = flightdata.flight_data(f, tables[f], spec.vehicle_for(f))
    apart, together = tmp_path / "apart", tmp_path / "together"
    sufficient.save(sufficient.compute_current(spec, f, tables[f], "log"), apart)
    library_stats.save(library_stats.compute(spec, f, tables[f], "log"), apart)
    sufficient.save(sufficient.compute_current(spec, f, tables[f], "log", shared), together)
    library_stats.save(library_stats.compute(spec, f, tables[f], "log", shared), together)
    for name in ("stats.bin", "library.bin", summaries.FILE_NAME):
        a, b = (sufficient.stats_path(root, f).parent / name for root in (apart, together))
        _same_file(a, b)
    layout = sufficient.spec_layout(spec)
    own = flightdata.flight_data(f, tables[f], spec.vehicle_for(f))
    rows = sufficient.design_rows(own, spec.vehicle, sufficient.Layout(layout.effects, layout.sizes))
    afresh = summaries.summarize(own, spec.vehicle, rows)
    stored = sufficient.load(together, f).summary()
    for name, arr in afresh.arrays().items():
        _same_array(getattr(stored, name), arr, name)
