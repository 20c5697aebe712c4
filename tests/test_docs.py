"""The documentation site builds with no broken link or anchor (``mkdocs build --strict``, the
configuration in mkdocs.yml), and its generated reference pages (the CLI from the argparse parser,
the JSON keys from their pinned list) match the code: they cannot drift."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _generator():
    spec = importlib.util.spec_from_file_location("gen_reference", REPO / "docs" / "gen_reference.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_generated_reference_pages_match_the_code():
    assert _generator().stale() == [], "run `make docs` (python docs/gen_reference.py) and commit the pages"


def test_the_cli_page_lists_every_verb():
    from quadcore.cli import build_parser

    page = (REPO / "docs" / "reference" / "cli.md").read_text()
    verbs = [v for v, _, _ in _generator()._parsers(build_parser())]
    assert len(verbs) >= 10
    assert all(f"## quadcore {v}\n" in page for v in verbs)


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None, reason="mkdocs is not installed (the dev extra)")
def test_the_site_builds_strictly(tmp_path):
    """Strict: a link to a page or an anchor that does not exist fails the build (mkdocs.yml's
    validation), so the docs cannot point at nothing. Not --quiet: mkdocs then never sees its own
    warnings and a broken link passes."""
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-4000:]
    assert (site / "index.html").exists() and (site / "reference" / "cli" / "index.html").exists()
    shutil.rmtree(site)


def test_every_environment_variable_the_code_reads_is_in_the_configuration_reference():
    import re

    read = re.compile(r"(?:environ(?:\.get)?[\[(]|getenv\()\s*\"(QUADCORE_\w+)\"")
    names = {m for path in [*(REPO / "quadcore").rglob("*.py"), *(REPO / "pipeline").rglob("*.py")]
             for m in read.findall(path.read_text())}
    assert len(names) >= 10
    page = (REPO / "docs" / "reference" / "configuration.md").read_text()
    assert sorted(n for n in names if f"`{n}`" not in page) == []


def test_the_readme_links_point_at_files_that_exist():
    """The README is not part of the site (GitHub shows it): its relative links are checked here."""
    import re

    links = re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", (REPO / "README.md").read_text())
    assert len(links) > 10
    assert [link for link in links if not (REPO / link).exists()] == []
