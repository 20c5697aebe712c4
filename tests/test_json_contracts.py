"""The JSON contracts of ``quadcore diagnose --json`` and ``quadcore discover --json``, pinned
byte for byte on a small deterministic simulated fleet (``drag_fleet``): a refactor of how the
results are built or typed must give the same documents, to the last digit."""

from __future__ import annotations

import pytest
import snapshot

from quadcore import cli, effects


@pytest.fixture
def builtin_effects_only(monkeypatch):
    """The effect registry as a fresh process has it: a plugin another test loaded would join the
    diagnosis's candidates. (In process: a subprocess per document cost 1.5 s of CPU each.)"""
    builtin = effects.builtin_names()
    for name in [n for n in effects.registry() if n not in builtin]:
        monkeypatch.delitem(effects._REGISTRY, name)  # put back after the test


@pytest.mark.parametrize(("verb", "options", "name"), [
    ("diagnose", [], "diagnose_drag_fleet.json"),
    ("diagnose", ["--holdout", "sim003", "--effects", "rotor_drag"], "diagnose_drag_fleet_holdout.json"),
    ("discover", ["--holdout", "sim003"], "discover_drag_fleet.json"),
])
def test_the_json_documents_are_byte_for_byte_pinned(drag_fleet, tmp_path, capsys, builtin_effects_only, verb,
                                                     options, name):
    out = tmp_path / "out.json"
    code = cli.main([verb, str(drag_fleet), "--json", str(out), "--quiet", *options])
    assert code == 0, capsys.readouterr().err
    assert list(effects.registry()) == list(effects.builtin_names())
    snapshot.assert_matches(out.read_text().splitlines(), name, f"the JSON of `quadcore {verb}` on drag_fleet",
                            "tests/test_json_contracts.py")
