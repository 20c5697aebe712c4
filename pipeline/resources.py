"""Paths the pipeline reads and writes, configurable by environment variables.

- ``QUADCORE_DATA_ROOT``: the data root (default ``data`` in the working directory);
  outputs go under it (see ``quadcore.store.store``).
- ``QUADCORE_RAW_DIR``: the folder of incoming raw logs (default ``<root>/raw``). Point it
  at a read-only folder of logs to process them without copying. It must exist and hold logs.
- ``QUADCORE_ALLOW_SIMULATED=1``: let one data root hold simulated and real flights together
  (refused otherwise, see :func:`quadcore.workflows.demo.check_flight_kinds`).

The demo (six simulated flights) has a data root of its own, ``data/demo``: ``python -m pipeline
--demo`` (``make demo``), or ``make run`` on the default data root while ``data/raw`` holds no
logs (:func:`choose_demo`). It never simulates into a raw folder of yours.
"""


import os
import shlex
from pathlib import Path

import dagster as dg

from pipeline.cluster import services
from quadcore import workflows
from quadcore.commands import shown_path
from quadcore.learn import learners
from quadcore.logs.flight import discover_logs, find_log
from quadcore.store import store
from quadcore.store.store import as_root, is_remote


class SettingError(ValueError):
    """A ``QUADCORE_*`` environment setting that cannot be used (a user error: one line, exit 2)."""


def default_data_root() -> str:
    return os.environ.get("QUADCORE_DATA_ROOT", DEFAULT_ROOT)


def automation_status():
    """Sensors start running unless ``QUADCORE_AUTOMATION=off`` (e.g. to browse without processing)."""
    off = os.environ.get("QUADCORE_AUTOMATION", "on").lower() in ("off", "0", "false", "no")
    return dg.DefaultSensorStatus.STOPPED if off else dg.DefaultSensorStatus.RUNNING


def retrain_cron() -> str:
    """When the learned models retrain on new flights: ``QUADCORE_RETRAIN_CRON`` (cron, UTC),
    nightly at 02:00 by default."""
    cron = os.environ.get("QUADCORE_RETRAIN_CRON", "0 2 * * *")
    try:
        dg.AutomationCondition.cron_tick_passed(cron, "UTC")  # Dagster's own check of the string
    except Exception:  # dagster's check error is not public API
        raise SettingError(f"QUADCORE_RETRAIN_CRON={cron!r}: not a cron schedule (e.g. '0 2 * * *')") from None
    return cron


def learn_row_budget() -> int:
    """The learning stage's row budget: ``QUADCORE_LEARN_ROWS``, the most usable rows of its
    training flights one training run holds (above it, drawn evenly per flight; default
    :data:`quadcore.learn.learners.DEFAULT_ROW_BUDGET`). :class:`SettingError` for a bad value."""
    text = os.environ.get("QUADCORE_LEARN_ROWS", "").strip().replace("_", "")
    if not text:
        return learners.DEFAULT_ROW_BUDGET
    try:
        return learners.check_row_budget(int(text))
    except (ValueError, learners.LearningError):
        raise SettingError(f"QUADCORE_LEARN_ROWS={os.environ['QUADCORE_LEARN_ROWS']!r}: give a whole number of rows, "
                           f"at least 1000 (default {learners.DEFAULT_ROW_BUDGET})") from None


DEFAULT_ROOT = "data"  # the default data root (relative to the working directory: the repository's data/)
DEMO_FOLDER = "demo"  # the demo's own data root, inside the default one


def allow_simulated() -> bool:
    """``QUADCORE_ALLOW_SIMULATED``: simulated and real flights may share a data root."""
    return os.environ.get("QUADCORE_ALLOW_SIMULATED", "").lower() in ("1", "true", "yes", "on")


def _is_default(env: str, default: Path) -> bool:
    value = os.environ.get(env, "")
    return not value or Path(value).resolve() == default


def choose_demo(explicit: bool) -> bool:
    """Whether this job runs the demo; if so ``QUADCORE_DATA_ROOT`` is pointed at the demo's own
    root (``data/demo``, or the root given with ``--demo``), so that everything started from here
    (Dagster's processes included) uses it. The demo runs when asked (``explicit``), or on the
    default data root (``data``, raw folder ``data/raw``) while that raw folder holds no logs:
    the README's first ``make run``. Never where a raw folder was named."""
    default = Path(DEFAULT_ROOT).resolve()
    if explicit:
        if os.environ.get("QUADCORE_RAW_DIR"):
            raise SettingError("QUADCORE_RAW_DIR is set: the demo simulates its flights into its own data root's "
                               "raw folder; unset it to run the demo")
        if _is_default("QUADCORE_DATA_ROOT", default):
            os.environ["QUADCORE_DATA_ROOT"] = str(default / DEMO_FOLDER)
        return True
    if not (_is_default("QUADCORE_DATA_ROOT", default) and _is_default("QUADCORE_RAW_DIR", default / "raw")):
        return False
    raw = default / "raw"
    if raw.is_dir() and discover_logs(raw):
        return False
    os.environ["QUADCORE_DATA_ROOT"] = str(default / DEMO_FOLDER)
    os.environ.pop("QUADCORE_RAW_DIR", None)
    return True


def default_raw_dir() -> str:
    return os.environ.get("QUADCORE_RAW_DIR", "")


class DataRoot(dg.ConfigurableResource):
    """The data root and the raw-log folder."""

    root: str = "data"
    raw: str = ""  # empty: <root>/raw

    @property
    def root_path(self) -> Path:
        """The root folder, or a ``UPath`` for an object-store URL (``s3://bucket/prefix``)."""
        root = as_root(self.root)
        return root if is_remote(root) else root.resolve()

    @property
    def raw_path(self) -> Path:
        return Path(self.raw).resolve() if self.raw else self.root_path / "raw"

    def raw_log(self, flight: str) -> Path:
        """The raw log of a flight id (``FileNotFoundError`` if it is gone)."""
        return find_log(self.raw_path, flight)


def data_root_from_env() -> DataRoot:
    return DataRoot(root=default_data_root(), raw=default_raw_dir())


class ModelConfig(dg.ConfigurableResource):
    """The physics model: a model file (vehicle + effects, see ``model.toml``), or just a
    vehicle; an optional thrust-map override; and the flights held out of fitting.

    Environment: ``QUADCORE_MODEL`` (default ``model.toml`` if present), ``QUADCORE_VEHICLE``,
    ``QUADCORE_THRUST_MAP``, ``QUADCORE_EFFECTS`` (comma-separated: replaces the file's effect
    list), ``QUADCORE_HOLDOUT`` (comma-separated flight ids), ``QUADCORE_SESSIONS`` (a sessions
    file: groups of flights whose parameters may differ; default: groups found from the data).
    """

    model_file: str = ""
    vehicle: str = ""
    thrust_map: str = ""
    effects: str = ""
    holdout: str = ""
    sessions_file: str = ""

    def spec(self):
        """The model these settings ask for, its sessions file included:
        :func:`quadcore.workflows.resolve_model`, as the CLI does."""
        return workflows.resolve_model(self.model_file, self.vehicle, self.thrust_map,
                                       workflows.parse_names(self.effects), self.sessions_file)

    @property
    def holdout_flights(self) -> list[str]:
        """The flights named in ``holdout`` (empty: none held out; the diagnosis cross-validates,
        see :func:`quadcore.workflows.held_out`)."""
        return workflows.parse_names(self.holdout)


def model_file_from_env() -> tuple[str, str]:
    """(the model file a run uses, where that choice came from, in words): ``QUADCORE_MODEL``,
    else the data root's own ``model.toml`` (the demo writes one, so that later runs continue its
    story; it then takes precedence over ./model.toml), else ./model.toml, else none (the nominal
    vehicle). The path is absolute, so that a hint naming it is the file to edit."""
    given = os.environ.get("QUADCORE_MODEL", "")
    if given:
        return str(Path(given).resolve()), "QUADCORE_MODEL"
    root = data_root_from_env().root_path
    own = store.own_model_file(root)
    if own.is_file():
        repo = " (the data root's own model file; ./model.toml is not read while it exists)" \
            if Path("model.toml").is_file() else ""
        return str(own), f"the data root's model.toml{repo}"
    if Path("model.toml").is_file():
        return str(Path("model.toml").resolve()), "./model.toml (the data root has no model.toml of its own)"
    return "", "no model file: the nominal vehicle, no effects"


def model_config_from_env() -> ModelConfig:
    """The model from the environment; its file is :func:`model_file_from_env`'s."""
    return ModelConfig(
        model_file=model_file_from_env()[0],
        vehicle=os.environ.get("QUADCORE_VEHICLE", ""),
        thrust_map=os.environ.get("QUADCORE_THRUST_MAP", ""),
        effects=os.environ.get("QUADCORE_EFFECTS", ""),
        holdout=os.environ.get("QUADCORE_HOLDOUT", ""),
        sessions_file=os.environ.get("QUADCORE_SESSIONS", ""),
    )


def executor_from_env():
    """``QUADCORE_EXECUTOR``: empty (Dagster's default: steps in processes on this machine),
    ``in_process``, ``multiprocess``, or ``k8s`` (each step a Kubernetes Job; needs dagster-k8s,
    see deploy/kubernetes) or ``celery`` (needs dagster-celery)."""
    kind = os.environ.get("QUADCORE_EXECUTOR", "").strip().lower()
    if kind == "k8s":
        from dagster_k8s import k8s_job_executor  # type: ignore[import-not-found]

        return k8s_job_executor
    if kind == "celery":  # the broker and result backend: QUADCORE_CELERY_BROKER / _BACKEND (see pipeline.cluster)
        from dagster_celery import celery_executor

        broker = os.environ.get("QUADCORE_CELERY_BROKER", "")
        backend = os.environ.get("QUADCORE_CELERY_BACKEND", "") or "rpc://"
        return celery_executor.configured(services.celery_config(broker, backend)) if broker else celery_executor
    local = {"": None, "in_process": dg.in_process_executor, "multiprocess": dg.multiprocess_executor}
    if kind not in local:
        raise SettingError(f"QUADCORE_EXECUTOR={kind!r}: use in_process, multiprocess, k8s or celery")
    return local[kind]


# The settings that choose what `make run` and `make ui` work on (data, model, fit, learning, where
# the steps run), in the order a hint prints them; DAGSTER_HOME and PORT follow.
COMMAND_SETTINGS = ("QUADCORE_RAW_DIR", "QUADCORE_DATA_ROOT", "QUADCORE_MODEL", "QUADCORE_VEHICLE",
                    "QUADCORE_THRUST_MAP", "QUADCORE_EFFECTS", "QUADCORE_HOLDOUT", "QUADCORE_SESSIONS",
                    "QUADCORE_ALLOW_SIMULATED", "QUADCORE_LEARN_ROWS", "QUADCORE_RETRAIN_CRON", "QUADCORE_EXECUTOR",
                    "QUADCORE_CELERY_BROKER", "QUADCORE_CELERY_BACKEND", "QUADCORE_CLUSTER_URL")
PATH_SETTINGS = ("QUADCORE_RAW_DIR", "QUADCORE_MODEL", "QUADCORE_VEHICLE", "QUADCORE_SESSIONS")


def _bare_root(raw_given: bool) -> Path:
    """The data root a `make` target chooses with no ``QUADCORE_DATA_ROOT``: the demo's while
    ``data/raw`` holds no logs and no raw folder is named (:func:`choose_demo`), else ``data``."""
    default = Path(DEFAULT_ROOT).resolve()
    raw = default / "raw"
    demo = not raw_given and not (raw.is_dir() and discover_logs(raw))
    return default / DEMO_FOLDER if demo else default


def make_command(target: str, port: int | None = None) -> str:
    """``make TARGET`` as a hint prints it: preceded by every setting of this process that a bare
    ``make TARGET`` would not use (the raw folder, data root, model file, ..., as the tutorial
    writes them), so that it works on the same flights with the same model; ``port``: the UI's
    (``PORT=``, left out at 3000)."""
    root = data_root_from_env().root_path
    local = not is_remote(root)
    given = {k: os.environ[k] for k in COMMAND_SETTINGS if os.environ.get(k)}
    if local and "QUADCORE_RAW_DIR" in given and Path(given["QUADCORE_RAW_DIR"]).resolve() == root / "raw":
        del given["QUADCORE_RAW_DIR"]  # the data root's own raw folder: the default
    given.pop("QUADCORE_DATA_ROOT", None)
    if not local:
        given["QUADCORE_DATA_ROOT"] = str(root)
    elif root not in (_bare_root("QUADCORE_RAW_DIR" in given), Path(DEFAULT_ROOT).resolve()):
        given["QUADCORE_DATA_ROOT"] = str(root)  # (the default root: a bare `make` picks it or the demo's, as here)
    home = os.environ.get("DAGSTER_HOME", "")
    if home and (not local or Path(home).resolve() != root / ".dagster"):
        given["DAGSTER_HOME"] = home
    if port is not None and port != 3000:
        given["PORT"] = str(port)
    order = [*COMMAND_SETTINGS, "DAGSTER_HOME", "PORT"]
    shown = {k: shown_path(v) if k in (*PATH_SETTINGS, "DAGSTER_HOME") or (k == "QUADCORE_DATA_ROOT" and local)
             else v for k, v in given.items()}
    return " ".join([*(f"{k}={shlex.quote(shown[k])}" for k in order if k in shown), "make", target])
