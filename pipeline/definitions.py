"""The Dagster definitions: load with ``dagster dev -w workspace.yaml``."""

import dagster as dg

from pipeline.assets.decode import decoded_flight
from pipeline.assets.physics import residual_table, rollout_errors
from pipeline.resources import data_root_from_env, physics_model_from_env
from pipeline.sensors import raw_log_sensor

# Everything computed per flight partition (the sensor and the main job run these).
PER_FLIGHT = [decoded_flight, residual_table, rollout_errors]

defs = dg.Definitions(
    assets=[*PER_FLIGHT],
    sensors=[raw_log_sensor],
    resources={"data_root": data_root_from_env(), "physics": physics_model_from_env()},
)
