"""The package's layers import downwards only, and no module imports itself back.

Each package of ``pipeline`` has a rank (:data:`LAYERS`); a module may import its own
package and any package of a lower rank, never one above. Imports are read from the
source (every ``import`` and ``from ... import``, inside functions and under
``TYPE_CHECKING`` too), so a lazy import cannot hide an upward edge.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"

# Lowest first: each may import those before it.
LAYERS = (
    ("errors",),
    ("geometry",),
    ("session", "synth"),
    ("carve",),
    ("baseline",),
    ("reconstruct",),
    ("record", "calibrate"),
    ("run",),
    ("live",),
    ("measure",),
    ("cli", "accuracy_table", "__init__", "__main__"),
)
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}


def _module(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """The ``pipeline`` modules (or packages) that the file at ``path`` imports."""
    module = _module(path)
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "pipeline")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "pipeline":
                continue
            # ``from pkg import name`` imports the module pkg.name when there is one.
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.add(sub if _path(sub) is not None else target)
    found.discard(module)
    return found


def _path(module: str) -> Path | None:
    base = PACKAGE.parent.joinpath(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.exists():
            return candidate
    return None


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


GRAPH = {_module(p): _imports(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_package_has_a_layer() -> None:
    assert {_layer(m) for m in GRAPH} <= set(RANK), "a new package needs its place in LAYERS"


def test_imports_go_down() -> None:
    upward = [
        f"{module} -> {target}"
        for module, targets in sorted(GRAPH.items())
        for target in sorted(targets)
        if RANK[_layer(target)] > RANK[_layer(module)]
    ]
    assert not upward, "imports of a higher layer: " + ", ".join(upward)


def test_no_import_cycle() -> None:
    """Depth-first search over modules; a package's ``__init__`` counts as a module."""
    done: set[str] = set()
    path: list[str] = []

    def visit(module: str) -> None:
        if module in path:
            cycle = [*path[path.index(module) :], module]
            pytest.fail("import cycle: " + " -> ".join(cycle))
        if module in done:
            return
        path.append(module)
        for target in sorted(GRAPH.get(module, ())):
            visit(target)
        path.pop()
        done.add(module)

    for module in sorted(GRAPH):
        visit(module)


def test_the_public_api_shows_in_dir_and_a_missing_name_says_so() -> None:
    import pipeline

    assert set(pipeline.__all__) <= set(dir(pipeline))
    with pytest.raises(AttributeError, match=r"module 'pipeline' has no attribute 'procss_session'"):
        pipeline.procss_session  # noqa: B018
