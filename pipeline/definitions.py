"""The Dagster definitions: load with ``dg dev -w workspace.yaml`` (``make ui``)."""

import warnings

import dagster as dg

from pipeline.assets import EXPORT, FLEET, LEARNING, PER_FLIGHT, PLANNING
from pipeline.resources import (
    automation_status,
    data_root_from_env,
    executor_from_env,
    model_config_from_env,
)
from pipeline.schedules import nightly_retrain_learned_models, retrain_learned_models
from pipeline.sensors import QUARANTINE, process_flight, raw_log_sensor

# Running them on the code server is "beta" in Dagster 1.13; it is what custom conditions need.
warnings.filterwarnings("ignore", message="Parameter `use_user_code_server`", category=dg.BetaWarning)

# Evaluates the automation conditions (retraining when flights arrive, refreshing stale flights).
# On the code server: pipeline.freshness's conditions are Python the daemon cannot run itself.
automation = dg.AutomationConditionSensorDefinition(
    "retrain_on_new_flights", target=dg.AssetSelection.all(), default_status=automation_status(),
    use_user_code_server=True,
)

defs = dg.Definitions(
    assets=[*PER_FLIGHT, *FLEET, *PLANNING, QUARANTINE, *LEARNING, *EXPORT],
    jobs=[process_flight, retrain_learned_models],
    sensors=[raw_log_sensor, automation],
    schedules=[nightly_retrain_learned_models],
    resources={"data_root": data_root_from_env(), "model": model_config_from_env()},
    executor=executor_from_env(),
)


def process_flight_job():
    """``process_flight`` for ``dg.reconstructable``: executors that run steps in other processes
    (multiprocess, Celery, Kubernetes) import it from here."""
    return defs.resolve_job_def("process_flight")
