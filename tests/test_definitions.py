"""A snapshot of the Dagster definitions: every asset (with its group, partitioning and
upstream assets), asset check, sensor and job, by key.

A change to the graph is then a reviewed change to ``tests/snapshots/dagster_definitions.txt``
instead of a surprise in the UI. After adding or renaming an asset, check, sensor or job, update
the snapshot with::

    QUADCORE_UPDATE_SNAPSHOT=1 python -m pytest tests/test_definitions.py

and commit the file with the change.
"""

from __future__ import annotations

import dagster as dg
import snapshot

SNAPSHOT = snapshot.FOLDER / "dagster_definitions.txt"


def definitions_lines(defs) -> list[str]:
    """One sorted line per asset, asset check, sensor, schedule and job (Dagster's internal jobs left out)."""
    graph = defs.resolve_asset_graph()
    lines = []
    for key in graph.get_all_asset_keys():
        node = graph.get(key)
        parts = node.partitions_def
        partitioned = getattr(parts, "name", None) or (type(parts).__name__ if parts else "-")
        upstream = ", ".join(sorted(k.to_user_string() for k in node.parent_keys)) or "-"
        lines.append(f"asset {key.to_user_string()}  group={node.group_name}  partitions={partitioned}  "
                     f"upstream={upstream}")
    lines += [f"check {key.asset_key.to_user_string()}:{key.name}" for key in graph.asset_check_keys]
    repo = defs.get_repository_def()
    lines += [f"sensor {s.name}" for s in repo.sensor_defs]
    lines += [f"schedule {s.name}" for s in repo.schedule_defs]
    lines += [f"job {j.name}" for j in repo.get_all_jobs() if not j.name.startswith("__")]
    return sorted(lines)


def test_definitions_match_the_snapshot(monkeypatch, tmp_path):
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(tmp_path))  # importing the definitions reads the env
    from pipeline.definitions import defs

    snapshot.assert_matches(definitions_lines(defs), SNAPSHOT.name, "the Dagster definitions",
                            "tests/test_definitions.py")


def test_the_snapshot_covers_every_kind():
    """The snapshot holds each kind the pipeline has (an enumeration that broke would otherwise
    write, and then match, a snapshot without it)."""
    kinds = {line.split(" ", 1)[0] for line in SNAPSHOT.read_text().splitlines()}
    assert {"asset", "check", "sensor", "job"} <= kinds


def test_the_main_job_stages_follow_the_graph(monkeypatch, tmp_path):
    """``python -m pipeline`` decodes first (DECODE), then each flight's statistics (STATISTICS,
    which the fit combines), and computes the per-flight tables after the fit (AGAINST_MODEL):
    the split is by what each asset depends on, not by list order."""
    monkeypatch.setenv("QUADCORE_DATA_ROOT", str(tmp_path))
    from pipeline.assets import AGAINST_MODEL, DECODE, PER_FLIGHT, STATISTICS
    from pipeline.definitions import defs

    graph = defs.resolve_asset_graph()
    model_key = dg.AssetKey("physics_model")
    stages = [set(DECODE), set(STATISTICS), set(AGAINST_MODEL)]
    assert set.union(*stages) == set(PER_FLIGHT) and sum(map(len, stages)) == len(PER_FLIGHT)
    for asset in STATISTICS:
        assert model_key not in graph.get_ancestor_asset_keys(asset.key), asset.key
        assert asset.key in graph.get_ancestor_asset_keys(model_key), asset.key
    for asset in DECODE:
        assert model_key not in graph.get_ancestor_asset_keys(asset.key), asset.key
    for asset in AGAINST_MODEL:
        assert model_key in graph.get_ancestor_asset_keys(asset.key), asset.key
