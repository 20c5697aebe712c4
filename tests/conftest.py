"""Shared fixtures: the real Crazyflie logs, and small synthetic logs built with the encoder.

The real logs are read in place (never copied into the repository). Tests that need them
are skipped, with the reason, on a machine without the shared data set.
"""

from __future__ import annotations

import os

# One BLAS (OpenBLAS, MKL) and OpenMP thread in every test process and every process a test starts
# (set before numpy loads its BLAS): the suite's numbers do not depend on the machine's cores or
# on how many pytest-xdist workers share them (make test runs two), and two workers on two cores
# do not wait for each other's BLAS threads.
os.environ.update(dict.fromkeys(("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"), "1"))

import struct  # noqa: E402
import tempfile  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from quadcore.logs import logformat  # noqa: E402

REAL_LOGS = Path(__file__).resolve().parents[1].parent / "shared" / "crazyflie" / "logs"


@pytest.fixture(scope="session", autouse=True)
def one_blas_thread():
    """One BLAS thread in this process also where a plugin loaded numpy before this file set the
    variables above (threadpoolctl limits the loaded libraries)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield


@pytest.fixture(autouse=True)
def no_plugin_effect_outlives_its_test():
    """Forget the plugin effects a test registered (a model file's ``plugins``, ``load_plugin``)
    when it ends. The registry is process-wide: a plugin left behind changed what a later test in
    the same worker saw (``sufficient.library_layout`` lists every registered effect), and a later
    ``unregister`` of the same name broke a layout built in between, so a test passed or failed
    with the order pytest-xdist gave it. Plugins a module- or session-scoped fixture registered
    are already there when this snapshot is taken, and stay for the fixture's life."""
    from quadcore import effects

    before = set(effects.registry())
    yield
    for name in set(effects.registry()) - before:
        effects.unregister(name)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """Under ``--dist loadscope`` (make test): the tests of a group on one worker
    (tests/scheduling.py)."""
    if config.getoption("dist") == "loadscope":
        import scheduling

        return scheduling.GroupScheduling(config, log)
    return None


def pytest_collection_modifyitems(config, items):
    """On an xdist worker: the costliest groups first (tests/scheduling.py; the scheduler hands
    out the groups in this order)."""
    if hasattr(config, "workerinput"):
        import scheduling

        items[:] = scheduling.order(items)


@pytest.fixture(scope="session", autouse=True)
def unsynced_dagster_test_instances(tmp_path_factory):
    """``dg.instance_for_test()`` makes its Dagster home with ``tempfile``: here, in a folder
    whose SQLite files are written without fsync, as the headless main job's are
    (:func:`pipeline.run.instance.unsynced_event_log`). About ten fsyncs per event otherwise: most of
    a Dagster test's time on a busy disk, for run records thrown away after the test."""
    from pipeline.run.instance import unsynced_event_log

    folder = tmp_path_factory.mktemp("dagster_instances")
    unsynced_event_log(folder)
    saved, tempfile.tempdir = tempfile.tempdir, str(folder)
    yield
    tempfile.tempdir = saved


@pytest.fixture(scope="session")
def real_logs() -> Path:
    """The folder of the 19 real uSD logs (``<clone>/../shared/crazyflie/logs``); read-only."""
    if not REAL_LOGS.is_dir():
        pytest.skip(f"real Crazyflie logs not found at {REAL_LOGS}: the shared data set is absent on this machine")
    return REAL_LOGS


# ---------------------------------------------------------------------------------------
# Simulated flights, made once per session and shared (read-only: link or copy them)
# ---------------------------------------------------------------------------------------

# The effect hidden in the shared fleet, and its true parameters (SI).
FLEET_EFFECT = {"rotor_drag": {"k_x_s_per_m": 0.15, "k_y_s_per_m": 0.15}}


@pytest.fixture(scope="session")
def drag_fleet(tmp_path_factory) -> Path:
    """Four random go-to flights (``sim000``..``sim002`` of 5 s, ``sim003`` of 3 s) with
    ``FLEET_EFFECT`` hidden, as uSD logs with their ``.truth.json``: the pipeline and operations
    tests share them. Four, so that with the last one held out (the flight the learned models are
    scored on) discovery still has three training flights to cross-validate over."""
    from quadcore.sim import simulation

    folder = tmp_path_factory.mktemp("drag_fleet")
    configs = [simulation.SimConfig(kind="random", duration_s=d, seed=s) for s, d in ((21, 5.0), (22, 5.0),
                                                                                    (23, 5.0), (24, 3.0))]
    simulation.simulate_set(folder, configs, FLEET_EFFECT)
    return folder


# ---------------------------------------------------------------------------------------
# Synthetic logs
# ---------------------------------------------------------------------------------------

# Two event types with different record sizes and odd ids; "fast" has every type character.
FAST = logformat.EventType(
    event_id=0xFFFF,
    name="fast",
    variables=("u8", "i8", "u16", "i16", "u32", "i32", "f32", "f16"),
    type_chars=("B", "b", "H", "h", "I", "i", "f", "e"),
)
SLOW = logformat.EventType(
    event_id=8,
    name="slow",
    variables=("pos.x", "half", "flag"),
    type_chars=("f", "e", "B"),
)
SYNTHETIC_TYPES = [FAST, SLOW]


@dataclass
class SyntheticLog:
    """A synthetic log: its bytes, where it was written, and what it holds."""

    version: int
    data: bytes
    path: Path
    event_types: list[logformat.EventType]
    values: dict[str, np.ndarray]  # event -> structured array (firmware units)
    timestamps_native: dict[str, np.ndarray]  # event -> timestamps as in the file (ms v1, us v2)
    timestamps_us: dict[str, np.ndarray]  # event -> timestamps in microseconds
    with_crc: bool

    def rows(self) -> dict[str, int]:
        return {name: len(v) for name, v in self.values.items()}


def _synthetic_values(et: logformat.EventType, n: int, rng: np.random.Generator) -> np.ndarray:
    values = np.empty(n, dtype=et.payload_dtype())
    for var, t in zip(et.variables, et.type_chars):
        dt = np.dtype(logformat.TYPE_CHARS[t])
        if dt.kind in "ui":
            info = np.iinfo(dt)
            col = rng.integers(info.min, info.max, size=n, endpoint=True, dtype=np.int64).astype(dt)
            col[: min(n, 2)] = [info.min, info.max][: min(n, 2)]  # the extremes
        else:
            col = rng.normal(0.0, 100.0, size=n).astype(dt)
            special = np.array([0.0, -0.0, 1.5, -2.25, np.finfo(dt).max, np.finfo(dt).tiny], dtype=dt)
            if dt == np.float16:
                special[-1] = np.float16(6e-8)  # a float16 subnormal
            k = min(n, len(special))
            col[:k] = special[:k]
        values[var] = col
    return values


@pytest.fixture
def make_synthetic_log(tmp_path):
    """Factory: ``make_synthetic_log(version=2, n_fast=40, n_slow=17, with_crc=True, name=...)``.

    Builds a log with :func:`quadcore.logs.logformat.encode` holding two interleaved event
    types (ids 0xFFFF and 8, record sizes differing), writes it under ``tmp_path`` and
    returns a :class:`SyntheticLog`. Timestamps: "fast" every 2 ms, "slow" every 5 ms
    from an offset, so records interleave irregularly and some timestamps coincide.
    """

    def make(version: int = 2, n_fast: int = 40, n_slow: int = 17, with_crc: bool = True,
             name: str | None = None, seed: int = 0) -> SyntheticLog:
        rng = np.random.default_rng(seed)
        to_us = logformat.TIMESTAMP_TO_US[version]
        base_ms = 4_000_000_000 if version == 1 else 5_000_000_000  # near u32's top in v1; > u32 in v2 (us)
        base = base_ms - 1000 if version == 1 else base_ms * 1000
        step_fast, step_slow, offset = (2, 5, 3) if version == 1 else (2000, 5000, 3000)
        ts = {
            "fast": base + step_fast * np.arange(n_fast, dtype=np.int64),
            "slow": base + offset + step_slow * np.arange(n_slow, dtype=np.int64),
        }
        values = {"fast": _synthetic_values(FAST, n_fast, rng), "slow": _synthetic_values(SLOW, n_slow, rng)}
        data = logformat.encode(
            SYNTHETIC_TYPES, [(n, ts[n], values[n]) for n in ("fast", "slow")], version=version, with_crc=with_crc
        )
        path = tmp_path / (name or f"synthetic_v{version}")
        path.write_bytes(data)
        return SyntheticLog(
            version=version, data=data, path=path, event_types=list(SYNTHETIC_TYPES), values=values,
            timestamps_native=ts, timestamps_us={k: v * to_us for k, v in ts.items()}, with_crc=with_crc,
        )

    return make


# ---------------------------------------------------------------------------------------
# An independent, deliberately plain reading of the format (for expected values in tests)
# ---------------------------------------------------------------------------------------

def _cstring(buf: bytes, pos: int) -> tuple[str, int]:
    end = buf.index(b"\x00", pos)
    return buf[pos:end].decode("ascii"), end + 1


def reference_records(buf: bytes, end: int | None = None) -> list[tuple[int, int, int]]:
    """``(offset, event_id, size)`` of every complete record, walking one record at a time.

    ``end`` is where the records stop (default: before the 4-byte CRC trailer). The walk
    stops at an unknown event id or at a record that does not fit.
    """
    version, n_types = struct.unpack_from("<HH", buf, 1)
    ts_size = {1: 4, 2: 8}[version]
    pos, sizes = 5, {}
    for _ in range(n_types):
        (eid,) = struct.unpack_from("<H", buf, pos)
        _, pos = _cstring(buf, pos + 2)
        (n_vars,) = struct.unpack_from("<H", buf, pos)
        pos += 2
        size = 2 + ts_size
        for _ in range(n_vars):
            spec, pos = _cstring(buf, pos)
            size += struct.calcsize("<" + spec[-2])
        sizes[eid] = size
    end = len(buf) - 4 if end is None else end
    out = []
    while pos + 2 <= end:
        (eid,) = struct.unpack_from("<H", buf, pos)
        if eid not in sizes or pos + sizes[eid] > end:
            break
        out.append((pos, eid, sizes[eid]))
        pos += sizes[eid]
    return out


@pytest.fixture(scope="session")
def record_offsets():
    """The plain per-record walker :func:`reference_records`, as a fixture."""
    return reference_records
