"""Every import of ``dcuscope.*`` resolves through the file system, as an editor or a type checker
resolves it: mypy's own module finder, given the checkout and nothing else, finds each module our
code and tests import at a file of ``dcuscope/``. No import hook, ``__path__`` entry or install
is needed to see the graph that ``tests/test_layers.py`` checks."""

from __future__ import annotations

import ast
from pathlib import Path

from mypy.modulefinder import FindModuleCache, SearchPaths
from mypy.options import Options

REPO = Path(__file__).resolve().parents[1]


def imports(path: Path) -> set[tuple[str, str | None]]:
    """(module, name) of each absolute ``dcuscope`` import: ``from A import b`` gives (A, b)."""
    out: set[tuple[str, str | None]] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {(alias.name, None) for alias in node.names if alias.name.split(".")[0] == "dcuscope"}
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "dcuscope":
            out |= {(node.module, alias.name) for alias in node.names}
    return out


def test_every_dcuscope_import_resolves_to_a_file_of_the_package():
    finder = FindModuleCache(SearchPaths(python_path=(str(REPO),), mypy_path=(), package_path=(), typeshed_path=()),
                             None, Options())
    package = (REPO / "dcuscope").resolve()
    seen: dict[str, str] = {}
    unresolved = []
    files = [p for folder in ("dcuscope", "tests", "benchmarks") for p in sorted((REPO / folder).rglob("*.py"))
             if "_build" not in p.parts and "node_modules" not in p.parts]
    for path in files:
        for module, name in sorted(imports(path), key=str):
            candidates = [f"{module}.{name}", module] if name else [module]  # ``from A import b``: b a module, or a name of A
            found = [str(seen.setdefault(c, finder.find_module(c))) for c in candidates]
            where = next((f for f in found if f.endswith(".py")), None)
            if where is None or not Path(where).resolve().is_relative_to(package):
                unresolved.append(f"{path.relative_to(REPO)}: {module}{'.' + name if name else ''} -> {found}")
    assert len(seen) > 300, f"only {len(seen)} imports read: the walk missed the code"
    assert not unresolved, "imports a type checker cannot find in dcuscope/:\n" + "\n".join(unresolved)
