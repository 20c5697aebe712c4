"""What to train: a learner spec (``xgboost`` gradient-boosted trees or an ``mlp``, with their
hyper-parameters, parsed from strings like ``xgboost:depth=6``), the training configuration
(subsampling stride, validation share, seed, threads) and the learning stage's error.
The whole learning stage is described in ``docs/learning.md``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

KINDS = ("xgboost", "mlp")


class LearningError(ValueError):
    """A request the learning stage cannot meet (unknown kind, too few flights, ...)."""


@dataclass(frozen=True)
class LearnerSpec:
    """Hyper-parameters of one learned model (not to be confused with :class:`quadcore.spec.model.ModelSpec`,
    the physics model a model file asks for). XGBoost uses ``max_depth``, ``n_estimators`` (the most
    trees per output; early stopping keeps fewer), ``learning_rate``, ``subsample``,
    ``min_child_weight``, ``early_stopping_rounds``; the MLP ``hidden`` (widths of the hidden
    layers, () = linear), ``lr``, ``batch_size``, ``max_epochs``, ``patience``, ``weight_decay``."""

    kind: str
    max_depth: int = 6
    n_estimators: int = 1000
    learning_rate: float = 0.1
    subsample: float = 0.8
    min_child_weight: float = 5.0
    early_stopping_rounds: int = 30
    hidden: tuple[int, ...] = (64, 64)
    lr: float = 1e-3
    batch_size: int = 256
    max_epochs: int = 200
    patience: int = 20
    weight_decay: float = 0.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise LearningError(f"unknown model kind {self.kind!r}; known: {', '.join(KINDS)}")

    @property
    def slug(self) -> str:
        if self.kind == "xgboost":
            return f"xgboost-d{self.max_depth}"
        return "mlp-" + ("x".join(map(str, self.hidden)) if self.hidden else "linear")

    @property
    def label(self) -> str:
        if self.kind == "xgboost":
            return f"xgboost(depth {self.max_depth}, <= {self.n_estimators} trees/output, eta {self.learning_rate:g})"
        layers = f"{len(self.hidden)} hidden: {'x'.join(map(str, self.hidden))}" if self.hidden else "0 hidden (linear)"
        return f"mlp({layers})"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> LearnerSpec:
        d = dict(d)
        d["hidden"] = tuple(d.get("hidden", ()))
        return cls(**d)


def default_spec(kind: str) -> LearnerSpec:
    return LearnerSpec(kind)


def parse_spec(text: str) -> LearnerSpec:
    """``xgboost``, ``xgboost:depth=4,trees=300,eta=0.1``, ``mlp:hidden=64x64,epochs=100``."""
    kind, _, rest = text.strip().partition(":")
    kind = kind.strip()
    if kind not in KINDS:
        raise LearningError(f"unknown model kind {kind!r}; known: {', '.join(KINDS)}")
    aliases = {"depth": "max_depth", "trees": "n_estimators", "eta": "learning_rate", "epochs": "max_epochs",
               "batch": "batch_size"}
    kw: dict = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = aliases.get(key.strip(), key.strip())
        if not eq or key not in LearnerSpec.__dataclass_fields__ or key == "kind":
            raise LearningError(f"bad model option {item!r} in {text!r}")
        try:
            if key == "hidden":
                kw[key] = tuple(int(h) for h in value.split("x") if h.strip()) if value.strip() not in ("", "0") else ()
            elif key in ("max_depth", "n_estimators", "early_stopping_rounds", "batch_size", "max_epochs", "patience"):
                kw[key] = int(value)
            else:
                kw[key] = float(value)
        except ValueError:
            raise LearningError(f"bad value in model option {item!r}") from None
    return LearnerSpec(kind, **kw)


def complexity_specs(kind: str) -> list[LearnerSpec]:
    """The complexity sweep of the comparison tables: tree depth 2/4/6/8; MLP 0/1/2 hidden layers."""
    if kind == "xgboost":
        return [replace(default_spec(kind), max_depth=d) for d in (2, 4, 6, 8)]
    return [replace(default_spec(kind), hidden=h) for h in ((), (64,), (64, 64))]


# The row budget: the most usable rows of its training flights one training run holds (fitting
# and validation rows, before the stride). Above it the rows are drawn evenly per flight with the
# seed (quadcore.learn.splits.budget_rows), so that training time and memory stop growing with
# the fleet. The 19 real flights' training flights hold 171,373 usable rows (jana02 held out):
# below it, so nothing changes there.
DEFAULT_ROW_BUDGET = 250_000


def check_row_budget(rows: int) -> int:
    """``rows`` if it can be a row budget (an integer of at least 1,000), else :class:`LearningError`."""
    if isinstance(rows, bool) or not isinstance(rows, int) or rows < 1000:
        raise LearningError(f"row budget {rows!r}: give a whole number of rows, at least 1000 "
                            f"(default {DEFAULT_ROW_BUDGET})")
    return rows


@dataclass
class TrainConfig:
    stride: int = 5  # use every stride-th sample of the fitting flights
    max_rows: int = DEFAULT_ROW_BUDGET  # the row budget (see DEFAULT_ROW_BUDGET)
    val_fraction: float = 0.2
    seed: int = 0
    # Threads for XGBoost and for torch: one each by default, measured on the 2-core machine
    # with the real flights. These models are small (~28k rows, <= 21 inputs), so a second
    # thread saves little when the machine is quiet and costs a lot when the other core is busy
    # (OpenMP synchronisation): best XGBoost 1.3 s on one thread vs 0.8 s on two when quiet,
    # 1.5 s vs 5.6 s when loaded; one MLP epoch 0.05 s on one thread vs 0.2-1.9 s on two.
    threads: int = 1
    torch_threads: int = 1
    # run_plan trains the XGBoost experiments and the MLPs side by side, one thread each (the
    # trees' C++ and torch's kernels release the GIL): the learning stage's wall time is then
    # the slower kind's, not their sum. 1: one after the other. The models are the same either
    # way (each kind has its own seeded state); only their training times are longer.
    lanes: int = 2

    def to_dict(self) -> dict:
        return asdict(self)
