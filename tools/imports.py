"""The import graph of quadcore and pipeline, read from the source with ast (nothing is imported).

`python tools/imports.py` prints the counts (modules, import cycles, function-level imports) and
`python tools/imports.py --write-docs` writes the stage packages' graph as a mermaid diagram into
docs/img/layers.mmd and into the mermaid block of docs/architecture.md. tests/test_import_graph.py
uses the same functions.

An import counts at any depth: module level, inside `if TYPE_CHECKING:` (excluded: never run),
and inside function bodies (a "function-level import", listed separately). `from a import b` counts
as an edge to `a.b` when `a.b` is a module, else to `a`; a package's `__init__` is its own node.
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


def _walk(node: ast.AST, function: str) -> Iterator[tuple[ast.Import | ast.ImportFrom, str]]:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and _is_type_checking(child):
            for sub in child.orelse:
                yield from _walk(sub, function)
            continue
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child, function
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


def imports(known: dict[str, Path] | None = None) -> list[Import]:
    """Every import edge between two of the packages' modules."""
    known = modules() if known is None else known
    edges: list[Import] = []
    for name, path in known.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node, function in _walk(tree, ""):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                mod = _resolve(name, node, known)
                targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
            for target in targets:
                while target and target not in known:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.append(Import(name, target, node.lineno, function))
    return sorted(set(edges), key=lambda e: (e.source, e.line, e.target))


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
    """`quadcore.identify.fitting` -> `identify`; pipeline modules -> `pipeline`."""
    parts = module.split(".")
    if parts[0] == "pipeline":
        return "pipeline"
    return parts[1] if len(parts) > 1 else "quadcore"


def mermaid(edges: list[Import]) -> str:
    """The stage packages' import graph (module-level and function-level edges) as mermaid text."""
    pairs: dict[tuple[str, str], bool] = {}
    for e in edges:
        a, b = stage(e.source), stage(e.target)
        if a != b and a != "quadcore" and b != "quadcore":
            pairs[(a, b)] = pairs.get((a, b), False) or not e.function
    lines = ["%% generated by: python tools/imports.py --write-docs",
             "%% solid: a module-level import; dotted: only inside functions", "graph TD"]
    for (a, b), module_level in sorted(pairs.items()):
        lines.append(f"  {a} {'-->' if module_level else '-.->'} {b}")
    return "\n".join(lines) + "\n"


MERMAID_FILE = "docs/img/layers.mmd"
ARCHITECTURE_PAGE = "docs/architecture.md"
FENCE = "```mermaid\n"


def with_block(page: str, text: str) -> str:
    """``page`` with its (first) mermaid code block's content replaced by ``text``."""
    start = page.index(FENCE) + len(FENCE)
    end = page.index("```", start)
    return page[:start] + text + page[end:]


def mermaid_block(page: str) -> str:
    """The content of ``page``'s first mermaid code block."""
    start = page.index(FENCE) + len(FENCE)
    return page[start:page.index("```", start)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write-docs", action="store_true",
                        help=f"write the stage graph to {MERMAID_FILE} and {ARCHITECTURE_PAGE}'s mermaid block")
    args = parser.parse_args()
    edges = imports()
    found = cycles(edges)
    inner = function_level(edges)
    print(f"modules: {len(modules())}, import edges: {len(edges)}")
    print(f"cycles: {len(found)} ({sum(map(len, found))} modules)")
    for c in found:
        print("  " + " <-> ".join(c))
    print(f"function-level imports: {len(inner)} "
          f"({sum(e.source.startswith('quadcore.identify') for e in inner)} in quadcore.identify)")
    if args.write_docs:
        text = mermaid(edges)
        (ROOT / MERMAID_FILE).write_text(text, encoding="utf-8")
        page = ROOT / ARCHITECTURE_PAGE
        page.write_text(with_block(page.read_text(encoding="utf-8"), text), encoding="utf-8")
        print(f"wrote {MERMAID_FILE} and {ARCHITECTURE_PAGE}")


if __name__ == "__main__":
    main()
