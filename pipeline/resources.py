"""Paths the pipeline reads and writes, configurable by environment variables.

- ``QUADCORE_DATA_ROOT``: the data root (default ``data`` in the working directory);
  outputs go under it (see ``quadcore.store``).
- ``QUADCORE_RAW_DIR``: the folder of incoming raw logs (default ``<root>/raw``). Point it
  at a read-only folder of logs to process them without copying.
"""


import os
from pathlib import Path

import dagster as dg


def default_data_root() -> str:
    return os.environ.get("QUADCORE_DATA_ROOT", "data")


def default_raw_dir() -> str:
    return os.environ.get("QUADCORE_RAW_DIR", "")


class DataRoot(dg.ConfigurableResource):
    """The data root and the raw-log folder."""

    root: str = "data"
    raw: str = ""  # empty: <root>/raw

    @property
    def root_path(self) -> Path:
        return Path(self.root).resolve()

    @property
    def raw_path(self) -> Path:
        return Path(self.raw).resolve() if self.raw else self.root_path / "raw"

    def raw_log(self, flight: str) -> Path:
        return self.raw_path / flight


def data_root_from_env() -> DataRoot:
    return DataRoot(root=default_data_root(), raw=default_raw_dir())


class PhysicsModel(dg.ConfigurableResource):
    """Which vehicle the model uses: a vehicle file path or a built-in name, and optionally
    a thrust map that overrides the file's (``pwm_vbat`` or ``motor_speed``).

    Environment: ``QUADCORE_VEHICLE``, ``QUADCORE_THRUST_MAP``.
    """

    vehicle: str = ""
    thrust_map: str = ""

    def load_vehicle(self):
        from quadcore import vehicle

        v = vehicle.load(self.vehicle or None)
        return v.with_thrust_map(self.thrust_map) if self.thrust_map else v


def physics_model_from_env() -> PhysicsModel:
    return PhysicsModel(
        vehicle=os.environ.get("QUADCORE_VEHICLE", ""), thrust_map=os.environ.get("QUADCORE_THRUST_MAP", "")
    )
