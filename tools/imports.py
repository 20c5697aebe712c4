"""The import graph of quadcore and pipeline, read from the source with ast (nothing is imported).

`python tools/imports.py` prints the counts (modules, import cycles) and every import made inside a function
(of the project's modules, of third-party packages and of the standard library alike), and
`python tools/imports.py --write-docs` writes the stage packages' graph and quadcore.identify's (its
modules and subpackages) as mermaid diagrams into docs/img/layers.mmd and docs/img/identify.mmd and into the
two mermaid blocks of docs/architecture.md. tests/test_import_graph.py
uses the same functions.

An import counts at any depth: module level, inside `if TYPE_CHECKING:` (excluded: never run),
and inside function bodies (a "function-level import", listed separately). `from a import b` counts
as an edge to `a.b` when `a.b` is a module, else to `a`; a package's `__init__` is its own node.
A call `importlib.import_module(f"quadcore.cli.{name}")` inside a function is a function-level import of
every module under its constant prefix (here `quadcore.cli.*`): it counts in the graph as an edge to each.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("quadcore", "pipeline")


@dataclass(frozen=True)
class Import:
    """One import statement's edge: `source` imports `target`; `function` names the enclosing def or ''."""

    source: str
    target: str
    line: int
    function: str


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the packages."""
    found: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _dynamic_prefix(node: ast.Call, module: str = "") -> str | None:
    """The known start of the module name an ``importlib.import_module(...)`` call in ``module`` imports
    (``"quadcore.cli."`` for ``f"quadcore.cli.{name}"``, ``{__name__}`` read as ``module``; ``""``: not known),
    or None if ``node`` is no such call."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    if name != "import_module" or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    prefix = ""
    for part in arg.values if isinstance(arg, ast.JoinedStr) else []:
        if isinstance(part, ast.Constant):
            prefix += str(part.value)
        elif (isinstance(part, ast.FormattedValue) and isinstance(part.value, ast.Name)
              and part.value.id == "__name__" and module):
            prefix += module
        else:
            break
    return prefix


Statement = ast.Import | ast.ImportFrom | ast.Call


def _walk(node: ast.AST, function: str) -> Iterator[tuple[Statement, str]]:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and _is_type_checking(child):
            for sub in child.orelse:
                yield from _walk(sub, function)
            continue
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child, function
        elif isinstance(child, ast.Call) and _dynamic_prefix(child) is not None:
            yield child, function
            yield from _walk(child, function)
        elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
            yield from _walk(child, child.name if not function else f"{function}.{child.name}")
        else:
            yield from _walk(child, function)


def _resolve(name: str, node: ast.ImportFrom, known: dict[str, Path]) -> str:
    if not node.level:
        return node.module or ""
    is_pkg = known[name].name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _named(name: str, node: Statement, known: dict[str, Path]) -> list[str]:
    """The module names an import statement names (a dynamic import: its constant prefix + ``*``)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.Call):
        return [f"{_dynamic_prefix(node, name)}*"]
    mod = _resolve(name, node, known)
    return [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]


def _statements(known: dict[str, Path]) -> Iterator[tuple[str, Statement, str]]:
    for name, path in known.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node, function in _walk(tree, ""):
            yield name, node, function


def imports(known: dict[str, Path] | None = None) -> list[Import]:
    """Every import edge between two of the packages' modules (a dynamic import: one to each module
    under its prefix)."""
    known = modules() if known is None else known
    edges: list[Import] = []
    for name, node, function in _statements(known):
        for named in _named(name, node, known):
            # a dynamic import: every module under its known prefix (none if nothing of it is known; never a
            # __main__, which is run, not imported)
            targets = ([m for m in known if named != "*" and m.startswith(named[:-1])
                        and not m.endswith(".__main__")] if named.endswith("*") else [named])
            for target in targets:
                while target and target not in known:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.append(Import(name, target, node.lineno, function))
    return sorted(set(edges), key=lambda e: (e.source, e.line, e.target))


def inner_imports(known: dict[str, Path] | None = None) -> list[Import]:
    """Every import made inside a function, of any module: the project's, a third-party package's or
    the standard library's (``target`` as written, absolute; a dynamic import's ends in ``*``)."""
    known = modules() if known is None else known
    found = {Import(name, target, node.lineno, function)
             for name, node, function in _statements(known) if function
             for target in _named(name, node, known) if target != "__future__"}
    return sorted(found, key=lambda e: (e.source, e.line, e.target))


def kind(target: str) -> str:
    """``project``, ``stdlib``, ``third-party`` or ``unknown`` (a dynamic import whose module name is not
    known before it runs): whose module an import names."""
    if target == "*":
        return "unknown"
    top = target.split(".")[0]
    if top in PACKAGES:
        return "project"
    return "stdlib" if top in sys.stdlib_module_names else "third-party"


def cycles(edges: list[Import]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted, sorted."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def function_level(edges: list[Import]) -> list[Import]:
    """The imports made inside a function body."""
    return [e for e in edges if e.function]


STAGES = ("store", "logs", "physics", "effects", "spec", "identify", "learn", "export", "sim", "plan",
          "report", "workflows", "cli")


def stage(module: str) -> str:
    """`quadcore.identify.fit.solve` -> `identify`; pipeline modules -> `pipeline`."""
    parts = module.split(".")
    if parts[0] == "pipeline":
        return "pipeline"
    return parts[1] if len(parts) > 1 else "quadcore"


def part(module: str, package: str) -> str:
    """The part of ``package`` that ``module`` is in: `quadcore.identify.diagnosis.run` -> `diagnosis` for
    `quadcore.identify` ('' when it is not in it, or is its ``__init__``)."""
    if not module.startswith(package + "."):
        return ""
    return module[len(package) + 1:].split(".")[0]


def mermaid(edges: list[Import], package: str = "") -> str:
    """The stage packages' import graph as mermaid text (module-level and function-level edges); with
    ``package``, the graph of that package's parts (its modules and subpackages) instead."""
    pairs: dict[tuple[str, str], bool] = {}
    for e in edges:
        a, b = (part(e.source, package), part(e.target, package)) if package else (stage(e.source), stage(e.target))
        if a != b and a not in ("", "quadcore") and b not in ("", "quadcore"):
            pairs[(a, b)] = pairs.get((a, b), False) or not e.function
    lines = [f"%% generated by: python tools/imports.py --write-docs{f' ({package})' if package else ''}",
             "%% solid: a module-level import; dotted: only inside functions", "graph TD"]
    for (a, b), module_level in sorted(pairs.items()):
        lines.append(f"  {a} {'-->' if module_level else '-.->'} {b}")
    return "\n".join(lines) + "\n"


ARCHITECTURE_PAGE = "docs/architecture.md"
# The pictures --write-docs makes: (file, the package it shows, '' for the stages), in the order of the
# page's mermaid blocks.
PICTURES = (("docs/img/layers.mmd", ""), ("docs/img/identify.mmd", "quadcore.identify"))
FENCE = "```mermaid\n"


def _block_span(page: str, index: int) -> tuple[int, int]:
    start = -1
    for _ in range(index + 1):
        start = page.index(FENCE, start + 1)
    start += len(FENCE)
    return start, page.index("```", start)


def with_block(page: str, text: str, index: int = 0) -> str:
    """``page`` with its ``index``-th mermaid code block's content replaced by ``text``."""
    start, end = _block_span(page, index)
    return page[:start] + text + page[end:]


def mermaid_block(page: str, index: int = 0) -> str:
    """The content of ``page``'s ``index``-th mermaid code block."""
    start, end = _block_span(page, index)
    return page[start:end]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write-docs", action="store_true",
                        help=f"write the stage graph and identify's to {', '.join(p for p, _ in PICTURES)} and "
                             f"{ARCHITECTURE_PAGE}'s mermaid blocks")
    args = parser.parse_args()
    edges = imports()
    if args.write_docs:
        page = ROOT / ARCHITECTURE_PAGE
        text = page.read_text(encoding="utf-8")
        for index, (path, package) in enumerate(PICTURES):
            picture = mermaid(edges, package)
            (ROOT / path).write_text(picture, encoding="utf-8")
            text = with_block(text, picture, index)
        page.write_text(text, encoding="utf-8")
        print(f"wrote {', '.join(p for p, _ in PICTURES)} and {ARCHITECTURE_PAGE}")
    found = cycles(edges)
    print(f"modules: {len(modules())}, import edges: {len(edges)}")
    print(f"cycles: {len(found)} ({sum(map(len, found))} modules)")
    for c in found:
        print("  " + " <-> ".join(c))
    every = inner_imports()
    counts = {k: sum(kind(e.target) == k for e in every) for k in ("project", "third-party", "stdlib", "unknown")}
    in_identify = sum(e.source.startswith("quadcore.identify") for e in every)
    print(f"imports inside functions: {len(every)} in {len({(e.source, e.function) for e in every})} functions "
          f"({', '.join(f'{n} {k}' for k, n in counts.items())}; {in_identify} in quadcore.identify):")
    for e in every:
        print(f"  {e.source}.{e.function}:{e.line} imports {e.target} ({kind(e.target)})")


if __name__ == "__main__":
    main()
