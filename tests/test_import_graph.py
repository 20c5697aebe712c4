"""No import cycle among quadcore's and pipeline's modules, and imports inside functions only on an allow-list.

The graph is read from the source with ast (tools/imports.py; nothing is imported), at any depth:
module-level imports and imports inside function bodies alike (`if TYPE_CHECKING:` blocks are left out:
they never run; a call `importlib.import_module(f"pkg.{name}")` counts as an import of every module of
`pkg`). A cycle is a strongly connected component of more than one module. The import-linter contracts
(pyproject.toml, make lint) hold the stage order and the packages' inner orders; this test holds the
module level.

ALLOWED is every import made inside a function, of any module (the project's, a third-party package's, the
standard library's), that may stay there: one entry per function, with the modules it may import and why
(start-up time or an optional dependency). At most twelve.

No import cycle anywhere (quadcore.identify's 7-module cycle went with the type dispatch, issue 23), and
every import inside a function, in quadcore.identify too, on the allow-list.
"""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import dataclass
from pathlib import Path

_PATH = Path(__file__).resolve().parents[1] / "tools" / "imports.py"
_spec = importlib.util.spec_from_file_location("quadcore_tools_imports", _PATH)
assert _spec is not None and _spec.loader is not None
graph = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = graph  # its dataclass looks itself up there
_spec.loader.exec_module(graph)


@dataclass(frozen=True)
class Lazy:
    """``module.function`` may import ``targets`` (a name covers its submodules; ``pkg.*``: a dynamic import
    of pkg's modules) inside its body, for ``reason``."""

    module: str
    function: str
    targets: tuple[str, ...]
    reason: str

    def covers(self, e) -> bool:
        return (e.source, e.function) == (self.module, self.function) and any(
            e.target == t or e.target.startswith(t + ".") for t in self.targets)


ALLOWED = (
    Lazy("quadcore.cli", "_load", ("quadcore.cli.*",),
         "start-up: a command group, with its stage and numpy/polars/scipy (0.5-1.6 s CPU), is imported when its "
         "command runs, so that `quadcore --help` loads none of them (test below; docs/benchmarks.md)"),
    Lazy("quadcore.effects", "_discover", ("quadcore.effects.*",),
         "the effect library is the package's modules, found by listing it: a new effect is a new module, named "
         "nowhere else"),
    Lazy("quadcore.learn.backends", "backend", ("quadcore.learn.backends.*",),
         "start-up and an optional dependency: torch and XGBoost take ~1.7 s of CPU each to import and load only "
         "when a model of their kind is trained, read or run; torch is installed outside the package's dependencies"),
    Lazy("quadcore.identify", "__getattr__", ("quadcore.identify.*",),
         "start-up: quadcore.identify's public names (fit_model, diagnose, discover, ...) load on first use, so "
         "that importing one identify module loads neither all of them nor scikit-learn (discovery)"),
    Lazy("quadcore.identify.stats.profiles", "_spline", ("scipy.interpolate",),
         "start-up: scipy.interpolate takes ~0.4 s to import; the profiles' spline is needed only between "
         "their grid points, in a fit or held-out test from statistics"),
    Lazy("quadcore.workflows.identify", "discover", ("quadcore.identify.discovery",),
         "start-up: scikit-learn (~1.1 s CPU) only for a discovery, not for every fit and diagnosis"),
    Lazy("quadcore.workflows.reports", "__getattr__", ("quadcore.report.*",),
         "start-up: the report modules import matplotlib (~0.5 s CPU); a workflow loads them when it writes a "
         "report, so that diagnose without --report, discover and plan start without them (docs/benchmarks.md)"),
    Lazy("quadcore.store.store", "as_root", ("upath",),
         "optional dependency: universal-pathlib (the s3 extra), only for a data root in an object store"),
    Lazy("pipeline.resources", "executor_from_env", ("dagster_celery", "dagster_k8s"),
         "optional dependencies: the cluster's executors (the cluster extra; Kubernetes), only when "
         "QUADCORE_EXECUTOR names one"),
    Lazy("pipeline.cluster.services", "start_store", ("boto3",),
         "optional dependency: boto3 (with moto, the dev extra) for the local cluster's S3 store only"),
)
MAX_ALLOWED = 12

IDENTIFY = "quadcore.identify"


def _inner() -> list:
    inner = graph.inner_imports()
    assert len(inner) > 5, "the reader finds (almost) no import inside a function: it is broken, not the code clean"
    return inner


def _not_allowed(inner: list) -> list[str]:
    return sorted(f"{e.source}:{e.line} imports {e.target} inside {e.function}()"
                  for e in inner if not any(lazy.covers(e) for lazy in ALLOWED))


def test_the_allow_list_is_short_and_each_entry_says_why() -> None:
    assert len(ALLOWED) <= MAX_ALLOWED, f"{len(ALLOWED)} entries: import at module level instead"
    assert len({(a.module, a.function) for a in ALLOWED}) == len(ALLOWED)
    assert all(len(a.reason) > 40 and a.targets for a in ALLOWED)


def test_every_allowed_import_is_still_made() -> None:
    """An entry no import inside its function needs any more goes (the list only shrinks)."""
    inner = _inner()
    stale = [f"{a.module}.{a.function}" for a in ALLOWED if not any(a.covers(e) for e in inner)]
    assert not stale, f"allow-list entries no longer used (remove them): {stale}"


def test_imports_inside_functions_only_on_the_allow_list_outside_identify() -> None:
    new = _not_allowed([e for e in _inner() if not e.source.startswith(IDENTIFY)])
    assert not new, ("imports inside functions not on the allow-list (import at module level, or add the function "
                     "with its reason to ALLOWED in tests/test_import_graph.py):\n" + "\n".join(new))


def test_imports_inside_functions_only_on_the_allow_list_in_identify() -> None:
    new = _not_allowed([e for e in _inner() if e.source.startswith(IDENTIFY)])
    assert not new, "imports inside functions in quadcore.identify not on the allow-list:\n" + "\n".join(new)


def test_no_import_cycle_outside_identify() -> None:
    found = [c for c in graph.cycles(graph.imports()) if not all(m.startswith(IDENTIFY) for m in c)]
    assert not found, "import cycles (break them; docs/architecture.md): " + "; ".join(" <-> ".join(c) for c in found)


def test_no_import_cycle_at_all() -> None:
    found = graph.cycles(graph.imports())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_reader_sees_a_cycle_it_is_given(tmp_path: Path) -> None:
    """The cycle finder on a made-up package: a -> b at module level, b -> a inside a function."""
    pkg = tmp_path / "quadcore"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from quadcore import b\n")
    (pkg / "b.py").write_text("def f():\n    from quadcore.a import x\n    return x\n")
    (tmp_path / "pipeline").mkdir()
    edges = graph.imports(graph.modules(tmp_path))
    assert graph.cycles(edges) == [["quadcore.a", "quadcore.b"]]
    inner = [(e.source, e.target, e.function) for e in graph.function_level(edges)]
    assert inner == [("quadcore.b", "quadcore.a", "f")]


def test_the_reader_sees_every_import_inside_a_function(tmp_path: Path) -> None:
    """Third-party, standard-library and dynamic imports inside functions are listed too, and a dynamic
    import of a package's modules is an edge to each of them (here closing a cycle)."""
    pkg = tmp_path / "quadcore"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "x.py").write_text("from quadcore import c\n")
    (pkg / "c.py").write_text("import importlib\n\ndef g(n):\n    import json\n    import numpy.linalg\n"
                              "    return importlib.import_module(f'quadcore.sub.{n}')\n")
    (tmp_path / "pipeline").mkdir()
    known = graph.modules(tmp_path)
    inner = [(e.target, graph.kind(e.target)) for e in graph.inner_imports(known)]
    assert inner == [("json", "stdlib"), ("numpy.linalg", "third-party"), ("quadcore.sub.*", "project")]
    assert graph.cycles(graph.imports(known)) == [["quadcore.c", "quadcore.sub.x"]]


def test_the_architecture_pictures_are_the_codes() -> None:
    """docs/img/layers.mmd, docs/img/identify.mmd and docs/architecture.md's two mermaid blocks are what
    `python tools/imports.py --write-docs` writes from the imports as they are now (re-run it after a change
    of layers)."""
    edges = graph.imports()
    root = Path(graph.ROOT)
    page = (root / graph.ARCHITECTURE_PAGE).read_text(encoding="utf-8")
    for index, (path, package) in enumerate(graph.PICTURES):
        text = graph.mermaid(edges, package)
        assert (root / path).read_text(encoding="utf-8") == text, path
        assert graph.mermaid_block(page, index) == text, f"{graph.ARCHITECTURE_PAGE}, mermaid block {index + 1}"


def test_each_packages_all_names_what_it_holds() -> None:
    """Every name in a quadcore package's ``__all__`` imports (a submodule or an attribute), and the old path
    of CCode (quadcore.export.ccode, kept for plugins) is the same class as the new one."""
    import importlib

    from quadcore.effects.ccode import CCode
    from quadcore.export.ccode import CCode as OldPathCCode

    assert OldPathCCode is CCode
    packages = sorted(p.parent.name for p in (Path(graph.ROOT) / "quadcore").glob("*/__init__.py"))
    assert len(packages) >= 10
    for name in packages:
        package = importlib.import_module(f"quadcore.{name}")
        assert package.__all__, name
        for public in package.__all__:
            found = hasattr(package, public) or importlib.util.find_spec(f"quadcore.{name}.{public}") is not None
            assert found, f"quadcore.{name}.__all__ names {public!r}, which it does not hold"


def test_the_cli_starts_without_the_numerical_libraries() -> None:
    """The reason the CLI loads a command group by name (quadcore.cli._load) holds: importing quadcore.cli
    (what `quadcore --help` runs) loads none of numpy, polars, scipy, matplotlib, scikit-learn, torch or Dagster."""
    import subprocess

    heavy = ("numpy", "polars", "scipy", "matplotlib", "sklearn", "torch", "dagster")
    code = f"import sys, quadcore.cli; print(' '.join(m for m in {heavy!r} if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert loaded == [], f"import quadcore.cli loads {loaded}: import them in the command group that needs them"


def test_diagnose_and_discover_start_without_matplotlib_and_a_report_loads_it() -> None:
    """The report modules (matplotlib) load when a report is written (quadcore.workflows.reports), not when
    the diagnose or discover command group is imported; asked for, ``reports.diagnosis`` is the module."""
    import subprocess

    code = ("import sys, quadcore.cli.diagnose, quadcore.cli.discover, quadcore.cli.learn; "
            "before = 'matplotlib' in sys.modules; "
            "from quadcore.workflows import reports; "
            "print(before, reports.diagnosis is sys.modules['quadcore.report.diagnosis'], 'matplotlib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "True", "True"]
