"""Where ``quadcore diagnose`` and ``quadcore discover`` will write is checked before the work:
an output folder that cannot be made is one line and exit code 2 at once, not after minutes of
fitting on a large fleet."""

from __future__ import annotations

import pytest

from quadcore import cli


@pytest.mark.parametrize("verb, option", [("diagnose", "--json"), ("diagnose", "--report"),
                                          ("discover", "--json"), ("discover", "--write-effect")])
def test_an_output_that_cannot_be_written_stops_before_the_work(drag_fleet, tmp_path, capsys, verb, option):
    blocker = tmp_path / "a-file"
    blocker.write_text("a file where a folder should be")
    good_json = str(tmp_path / "out.json")
    target = {"--json": str(blocker / "out.json"), "--report": str(blocker / "reports"),
              "--write-effect": str(blocker / "found.py")}[option]
    argv = [verb, str(drag_fleet), *(["--json", good_json] if option != "--json" else []), option, target]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert f"quadcore {verb}: error:" in err and "a-file" in err
    assert "fitting" not in err and "diagnosing" not in err and "Traceback" not in err
