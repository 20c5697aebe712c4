"""The one orchestration layer: the steps the command line and the Dagster assets share, so
both take the same decisions with the same checks and write the same outputs.

- :mod:`.fleet`: which flights (decoded, usable), which model, which flights are held out;
- :mod:`.identify`: fit, diagnose, discover, and write each result;
- :mod:`.learn`: residual and feature tables, training, the learning report, staleness.

The CLI keeps argument parsing and printing; an asset keeps loading, one call and metadata.
"""

from quadcore.workflows.fleet import (
    Fleet,
    HoldoutError,
    NoFlightsError,
    WorkflowError,
    held_out,
    named_holdout,
    parse_names,
    resolve_model,
)

__all__ = ["Fleet", "HoldoutError", "NoFlightsError", "WorkflowError", "held_out", "named_holdout", "parse_names",
           "resolve_model"]
