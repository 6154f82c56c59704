"""The house's arrows (docs: DESIGN "Layout"): app → models, app → analysis, never back, no
circle of imports among the app's modules, and app/services/ grouped by domain with the analysis
views above the other domains.

Read from the source (every ``import`` anywhere in a module, a function's own included, and
``importlib.import_module`` of a literal name), so a lazy import cannot hide an arrow that points
the wrong way.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.settings import REPO_ROOT

PACKAGES = ("app", "analysis", "models")
FORBIDDEN = {"analysis": {"app", "models"}, "models": {"app", "analysis"}}
"""What each package must never import: analysis knows pandas and statistics, models torch and
numpy; only app joins them."""


def _modules() -> dict[str, Path]:
    """Every module of the three packages by dotted name (a package by its own name)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((REPO_ROOT / package).rglob("*.py")):
            parts = path.relative_to(REPO_ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


MODULES = _modules()


def _imported(name: str, path: Path) -> Iterator[tuple[str, int]]:
    """The modules ``name`` imports (as dotted names, with the line), ``from x import y`` as
    ``x.y`` when ``y`` is a module of ours, else ``x``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif _is_import_module_call(node):
            yield node.args[0].value, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                yield (submodule if submodule in MODULES else base), node.lineno


def _is_import_module_call(node: ast.AST) -> bool:
    """``importlib.import_module("a.literal.name")``: an import by another name."""
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "import_module"
        and len(node.args) == 1
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    )


def _app_graph() -> dict[str, set[str]]:
    return {
        name: {
            target
            for target, _ in _imported(name, path)
            if target in MODULES and target.startswith("app") and target != name
        }
        for name, path in MODULES.items()
        if name.split(".")[0] == "app"
    }


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_analysis_and_models_never_import_the_packages_above_or_beside_them(
    package: str,
) -> None:
    wrong = {
        f"{path.relative_to(REPO_ROOT)}:{line} imports {target}"
        for name, path in MODULES.items()
        if name.split(".")[0] == package
        for target, line in _imported(name, path)
        if target.split(".")[0] in FORBIDDEN[package]
    }
    assert sorted(wrong) == []


def test_no_circle_of_imports_among_the_app_modules() -> None:
    assert _cycles(_app_graph()) == []


def test_the_cycle_finder_finds_a_circle() -> None:
    """The check above would pass on an empty answer: it must see a circle when there is one."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert "app.services.sessions.learners" in _app_graph()  # the graph is of the real modules


def test_an_import_by_importlib_is_an_import() -> None:
    source = 'import importlib\nengines = importlib.import_module("app.speech.engines")\n'
    assert [
        node.args[0].value for node in ast.walk(ast.parse(source)) if _is_import_module_call(node)
    ] == ["app.speech.engines"]


SERVICE_DOMAINS = ("participants", "sessions", "privacy", "analysis_views", "staff", "design")
SHARED_SERVICES = {"__init__", "audit", "studies", "blinding", "topics"}
"""app/services/ is grouped by domain (DESIGN "Growing the house, wave 4"); only what every domain
uses stays at its top."""


def test_every_service_module_lives_in_its_domain() -> None:
    services = REPO_ROOT / "app" / "services"
    flat = sorted(p.name for p in services.glob("*.py") if p.stem not in SHARED_SERVICES)
    assert flat == [], f"put each in one of app/services/{{{','.join(SERVICE_DOMAINS)}}}/"
    packages = sorted(p.name for p in services.iterdir() if (p / "__init__.py").exists())
    assert packages == sorted(SERVICE_DOMAINS)


def test_analysis_views_read_the_domains_and_no_domain_reads_them() -> None:
    """The views turn every domain's data into pages and files; a domain that imported a view
    would make its rules depend on how a page shows them."""
    wrong = sorted(
        f"{name} imports {target}"
        for name, targets in _app_graph().items()
        if name.startswith("app.services.") and not name.startswith("app.services.analysis_views")
        for target in targets
        if target.startswith("app.services.analysis_views")
    )
    assert wrong == []
