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
