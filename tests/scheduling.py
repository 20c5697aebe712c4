"""How ``make test`` shares the suite between its two pytest-xdist workers (``-n 2 --dist loadgroup
--no-loadscope-reorder``, docs/reference/testing.md).

Groups: the tests of one module run on one worker, so that a module's costly fixture (the
cluster, the running UI, a simulated fleet) and its per-process caches are made once. Two kinds
of test are independent of the rest of their module and costly alone, and get a group each:
the planner's separation trials (``test_plan.py``, one simulation and two diagnoses per seed)
and the independent-physics cases of one rotorpy fleet (``tests/independent``: the fleet's
decoded flights and diagnoses are cached per process, so all the cases of a fleet stay together).

Order: the costliest groups first (:data:`COST_S`, rough seconds of one CI run), so that no long
group starts last and runs alone. The order decides only which worker runs what and when; every
test is independent of both (per-test temporary folders, free ports, the rotorpy flights'
cache written whole under a lock)."""

from __future__ import annotations

import pytest

# Rough cost of a group in one CI run, in seconds on the 2-core CI machine (from `--durations`;
# a name ending in "-" stands for every group it begins); the rest keep their collection order.
COST_S = {
    "tests/test_cluster.py": 380,
    "plan-": 180,
    "tests/test_ui_live.py": 170,
    "rotorpy-": 100,  # the first to run also simulates the flights when the cache is empty
    "tests/test_bad_flights.py": 50,
}


def cost(name: str) -> float:
    """The group's rough cost (:data:`COST_S`), 0 where unknown."""
    return max((s for key, s in COST_S.items() if name == key or (key.endswith("-") and name.startswith(key))),
               default=0)


def group(item: pytest.Item) -> str:
    """The xdist group of a collected test (see the module)."""
    module = item.nodeid.split("::")[0]  # tests/test_x.py
    params = getattr(item, "callspec", None)
    if module == "tests/independent/test_rotorpy_physics.py":
        return f"rotorpy-{params.params.get('fleet', 'logs') if params else 'logs'}"
    if module == "tests/test_plan.py" and params and item.name.startswith("test_the_planned_flight_decides"):
        return f"plan-{params.id}"
    return module


def order(items: list[pytest.Item], groups: list[str]) -> list[pytest.Item]:
    """``items`` with the tests of a group together, the costliest group first (stable otherwise)."""
    first: dict[str, int] = {}
    for i, name in enumerate(groups):
        first.setdefault(name, i)
    key = {name: (-cost(name), i) for name, i in first.items()}
    return [item for _, item in sorted(zip(groups, items), key=lambda pair: key[pair[0]])]
