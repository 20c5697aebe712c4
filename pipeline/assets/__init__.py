"""The assets, by stage: the lists below are the one place that says which asset belongs to which
stage (the definitions, the sensor's job and the main job all take them from here)."""

from pipeline.assets.decode import decoded_flight
from pipeline.assets.discovery import term_discovery
from pipeline.assets.export import exported_model, flight_mcap
from pipeline.assets.learning import learned_models, learning_features, learning_report
from pipeline.assets.model import error_history, model_diagnosis, physics_model
from pipeline.assets.physics import residual_table, rollout_errors
from pipeline.assets.plan import flight_plan
from pipeline.assets.statistics import flight_statistics

# Computed per flight partition (the sensor's runs and the main job run these): decoding, which
# needs no model, then the tables computed against the fitted physics model.
DECODE = [decoded_flight]
# Each flight's sufficient statistics of the linear effects, which the fleet fit combines.
STATISTICS = [flight_statistics]
AGAINST_MODEL = [residual_table, rollout_errors, flight_mcap]
PER_FLIGHT = [*DECODE, *STATISTICS, *AGAINST_MODEL]
# Computed over all flights.
FLEET = [physics_model, term_discovery, model_diagnosis, error_history]
# The next flight to fly, from the stored diagnosis: materialised on demand or by its automation
# condition, not by the main job (its search takes minutes on a large fleet).
PLANNING = [flight_plan]
# Learned residual models on top of the physics model (fan-in over all residual tables).
LEARNING = [learning_features, learned_models, learning_report]
# The current model as C for the flight controller.
EXPORT = [exported_model]
