"""A small sample of the fuzz harness in the normal test run (the full run: make fuzz)."""

from __future__ import annotations

from fuzz import harness


def test_a_sample_of_mutants_meets_the_bar(tmp_path):
    logs, _ = harness.good_logs(None, count=1)
    summary = harness.run(logs, 40, tmp_path, seed=7, log=lambda m: None)
    assert summary.mutants == 40 and len(summary.by_kind) >= 10
    assert summary.untyped_errors == []
    assert summary.over_time == 0 and summary.files_outside_root == 0
    assert summary.prefix_checked > 0 and summary.prefix_lost == 0
    assert summary.body_corruptions > 0 and summary.recovered_median >= 0.9
    assert summary.phantom_checked > 0 and summary.phantoms == 0


def test_a_sample_of_the_structure_aware_cases_meets_the_bar(tmp_path):
    """Every family of tests/fuzz/structure.py, drawn evenly (the full run: make fuzz)."""
    from fuzz import structure

    logs, _ = harness.good_logs(None, count=2)
    tally = structure.run(logs[:1] + logs[1:], 20, seed=3, write_root=tmp_path / "root", limit=90,
                          log=lambda m: None)
    assert tally.cases == 180 and len(tally.by_family) >= 12, tally.by_family
    assert tally.tracebacks == [] and tally.hangs == 0
    assert tally.phantoms == 0, tally.phantom_cases
    assert tally.lost == 0, tally.lost_cases
    assert not [p for p in tmp_path.rglob("*") if p.is_file() and (tmp_path / "root") not in p.parents]
