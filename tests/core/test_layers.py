"""The engine's layers: a module imports only from its own layer or those below, and no
module imports another that (directly or through others) imports it back.

Imports are read with ``ast`` from every module of ``core/``, at module level and inside
functions alike (a deferred import is still a dependency), so nothing is imported here.
docs/architecture.md draws the same layers.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[2] / "core"

#: Lowest first. A top-level name of ``core`` (package or module) belongs to one layer.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("__init__", "errors", "config", "io_utils", "progress", "runtime")),
    ("formats", ("formats", "colmap", "datasets", "terrain", "metrics")),
    ("render", ("render",)),
    ("training", ("train",)),
    ("priors", ("priors", "ndn", "labels")),
    ("methods", ("methods",)),
    ("applications", ("apps", "experiments")),
    ("cli", ("commands", "cli", "__main__")),
]
LAYER_OF = {name: index for index, (_, names) in enumerate(LAYERS) for name in names}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(CORE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in sorted(CORE.rglob("*.py")) if "__pycache__" not in path.parts}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The core modules ``name`` imports anywhere in its file (``from . import x`` resolved
    to the submodule ``x`` when it is one)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    # imports under ``if TYPE_CHECKING:`` are for annotations only: never executed
    typing_only = {id(inner) for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node.test)
                   for statement in node.body for inner in ast.walk(statement)}
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.startswith("esgs.core"):
                target = node.module[len("esgs."):]
            else:
                continue
            for alias in node.names:
                submodule = f"{target}.{alias.name}"
                found.add(submodule if submodule in known else target)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("esgs.core"):
                    found.add(alias.name[len("esgs."):])
    return {module for module in found if module in known and module != name}


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) for name, path in modules.items()}


def _layer(module: str) -> int:
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    if top not in LAYER_OF:
        raise AssertionError(f"core.{top} is in no layer: add it to LAYERS (tests/core/test_layers.py) "
                             "and to docs/architecture.md")
    return LAYER_OF[top]


def test_every_top_level_name_of_core_has_a_layer():
    tops = {path.stem if path.is_file() else path.name for path in CORE.iterdir()
            if (path.suffix == ".py" or (path.is_dir() and (path / "__init__.py").is_file()))}
    assert sorted(tops - set(LAYER_OF)) == []
    assert sorted(set(LAYER_OF) - tops) == []


def test_no_module_imports_from_a_higher_layer():
    upward = []
    for module, imported in _graph().items():
        for target in imported:
            if _layer(target) > _layer(module):
                upward.append(f"{module} ({LAYERS[_layer(module)][0]}) imports {target} ({LAYERS[_layer(target)][0]})")
    assert upward == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = [0]

    def visit(node: str) -> None:
        index[node] = low[node] = counter[0]
        counter[0] += 1
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
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def _without_package_reexports(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """A package's ``__init__`` re-exporting its own submodules is not a dependency cycle:
    drop the edges from a package to the modules inside it."""
    return {module: {t for t in targets if not t.startswith(module + ".")} for module, targets in graph.items()}


def test_no_import_cycles_at_module_level_or_inside_functions():
    assert _cycles(_without_package_reexports(_graph())) == []


def test_the_checks_see_a_planted_violation(tmp_path, monkeypatch):
    """The graph reader finds relative imports inside functions, and the cycle finder finds cycles."""
    module = tmp_path / "core" / "train" / "x.py"
    module.parent.mkdir(parents=True)
    module.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .z import Z\n"
                      "def f():\n    from ..methods import registry\n    from . import y\n")
    known = {"core.methods.registry", "core.train.y", "core.methods", "core.train.z"}
    assert _imports("core.train.x", module, known) == {"core.methods.registry", "core.train.y"}
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    with pytest.raises(AssertionError, match="in no layer"):
        _layer("core.nowhere.module")
