"""How ``make test`` shares the suite between its two pytest-xdist workers (``-n 2 --dist loadscope
--no-loadscope-reorder`` with :class:`GroupScheduling`, docs/reference/testing.md).

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
from xdist.scheduler import LoadScopeScheduling  # type: ignore[import-untyped]

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


def group(nodeid: str) -> str:
    """The worker group of a test, from its node id alone (see the module)."""
    module, _, rest = nodeid.partition("::")
    name, _, params = rest.partition("[")
    params = params.rstrip("]")
    if module == "tests/independent/test_rotorpy_physics.py":
        fleet = params.split("-")[0]  # the case ids begin with the fleet (a rate alone: the logs' own test)
        return f"rotorpy-{fleet if fleet and not fleet.isdigit() else 'logs'}"
    if module == "tests/test_plan.py" and params and name.startswith("test_the_planned_flight_decides"):
        return f"plan-{params}"
    return module


class GroupScheduling(LoadScopeScheduling):
    """xdist's scheduling by scope, a scope being a :func:`group`. (xdist's own ``loadgroup``
    reads groups from node ids it rewrites, which pytest 9.2's structured node ids no longer allow:
    the groups would silently be lost.)"""

    def _split_scope(self, nodeid: str) -> str:
        return group(nodeid)


def order(items: list[pytest.Item]) -> list[pytest.Item]:
    """``items`` with the tests of a group together, the costliest group first (stable otherwise)."""
    groups = [group(item.nodeid) for item in items]
    first: dict[str, int] = {}
    for i, name in enumerate(groups):
        first.setdefault(name, i)
    key = {name: (-cost(name), i) for name, i in first.items()}
    return [item for _, item in sorted(zip(groups, items), key=lambda pair: key[pair[0]])]
