"""The JSON contracts of ``quadcore diagnose --json`` and ``quadcore discover --json``, pinned
byte for byte on a small deterministic simulated fleet (``drag_fleet``): a refactor of how the
results are built or typed must give the same documents, to the last digit."""

from __future__ import annotations

import subprocess
import sys

import pytest
import snapshot


@pytest.mark.parametrize(("verb", "options", "name"), [
    ("diagnose", [], "diagnose_drag_fleet.json"),
    ("diagnose", ["--holdout", "sim003", "--effects", "rotor_drag"], "diagnose_drag_fleet_holdout.json"),
    ("discover", ["--holdout", "sim003"], "discover_drag_fleet.json"),
])
def test_the_json_documents_are_byte_for_byte_pinned(drag_fleet, tmp_path, verb, options, name):
    """In a process of its own: a plugin effect another test registered would join the candidates."""
    out = tmp_path / "out.json"
    run = subprocess.run([sys.executable, "-m", "quadcore.cli", verb, str(drag_fleet), "--json", str(out), "--quiet",
                          *options], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    snapshot.assert_matches(out.read_text().splitlines(), name, f"the JSON of `quadcore {verb}` on drag_fleet",
                            "tests/test_json_contracts.py")
