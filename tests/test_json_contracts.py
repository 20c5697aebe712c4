"""The JSON contracts of ``quadcore diagnose --json`` and ``quadcore discover --json``, pinned on a
small deterministic simulated fleet (``drag_fleet``): a refactor of how the results are built or
typed must give the same documents: the same keys in the same order, the same text, the same
numbers to a relative tolerance (``snapshot.REL``, with an absolute floor near zero), not byte
for byte (another machine or BLAS thread count moves the last digits)."""

from __future__ import annotations

import json

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
def test_the_json_documents_are_pinned(drag_fleet, tmp_path, capsys, builtin_effects_only, verb,
                                                     options, name):
    out = tmp_path / "out.json"
    code = cli.main([verb, str(drag_fleet), "--json", str(out), "--quiet", *options])
    assert code == 0, capsys.readouterr().err
    assert list(effects.registry()) == list(effects.builtin_names())
    snapshot.assert_json_matches(out.read_text(), name, f"the JSON of `quadcore {verb}` on drag_fleet",
                                 "tests/test_json_contracts.py")
    if verb == "diagnose":
        _assert_held_out_levels(json.loads(out.read_text())["candidates"])


def _assert_held_out_levels(rows: list[dict]) -> None:
    """Each candidate's ``held_out_level`` names where its ``held_out_*`` fields and
    ``signal_to_noise`` were measured: a timing candidate (``Effect.retimes_thrust``, decided by
    ``rates.judge``) at the angular rates, every other one in its ``target`` channel."""
    from quadcore.identify.rates import RATE_LEVEL

    timing = {r["effect"] for r in rows if effects.get(r["effect"]).retimes_thrust}
    assert timing and len(timing) < len(rows), [r["effect"] for r in rows]
    for r in rows:
        assert r["held_out_level"] == (RATE_LEVEL if r["effect"] in timing else r["target"]), r
        assert r["target"] in ("force", "torque"), r


def test_the_pinned_documents_compare_numbers_to_a_tolerance_and_text_exactly():
    """The comparison the pins use: the last digits of a number may move (another machine,
    another BLAS thread count), its value may not; text, keys, their order and nulls may not."""
    doc = {"verdict": "Most likely missing: rotor_drag", "k": 0.15, "n": 4, "p": 2.8e-120, "ev": [1e-16, None]}
    same = snapshot.json_differences
    assert same({**doc, "k": 0.15 * (1 + 3e-10), "ev": [1.8e-15, None]}, doc) == []
    assert same({**doc, "k": 0.15 * (1 + 1e-5)}, doc) == [".k: 0.1500015 != 0.15"]
    assert same({**doc, "n": 5}, doc) and same({**doc, "verdict": "Most likely missing: wind"}, doc)
    assert same({**doc, "ev": [1e-16, 0.0]}, doc) and same(dict(reversed(doc.items())), doc)


def test_a_pinned_documents_candidates_read_back_as_typed_rows_that_stay_as_read():
    """Each candidate of a pinned diagnosis document read back (CandidateScore.from_dict, as the plan
    and the report read one) gives its JSON object again, key for key and in order, and the typed row
    is read-only: a field assigned after it is made is an error, not a silent change."""
    import dataclasses

    from quadcore.identify.diagnosis import CandidateScore

    doc = json.loads((snapshot.FOLDER / "diagnose_drag_fleet_holdout.json").read_text())
    assert len(doc["candidates"]) >= 10
    for row in doc["candidates"]:
        score = CandidateScore.from_dict(row)
        assert list(score.to_dict().items()) == list(row.items())
        with pytest.raises(dataclasses.FrozenInstanceError):
            score.found = not score.found
        assert score.found == row["found"]
    # a row without held_out_level (a document written before it) reads back with its target channel's
    row = {k: v for k, v in doc["candidates"][0].items() if k != "held_out_level"}
    assert CandidateScore.from_dict(row).held_out_level == row["target"]
