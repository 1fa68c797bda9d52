"""The package's three floors: the model (``platoon_opt/*.py``), the allocators
(``platoon_opt.solvers``) and the study (``platoon_opt.study``). Every import, at any depth of a
module (function-level ones included), points down or sideways, and no modules import each other
in a loop."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "platoon_opt"
FLOORS = {"model": 1, "solvers": 2, "study": 3}
# Libraries the model and the allocators must not need: plotting and the study's progress display.
STUDY_ONLY = ("matplotlib", "tqdm", "distributed")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def floor(module: str) -> int:
    parts = module.split(".")
    return FLOORS.get(parts[1], 1) if len(parts) > 1 else 1


def imports(path: Path, modules: set[str]) -> set[str]:
    """Every module ``path`` imports, absolute, at any depth of the file; ``from package import
    submodule`` counts as importing the submodule (of ``modules``), not the package's face."""
    found = set()
    package = module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else module_name(path)
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.update(
                f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names
            )
    return found


SOURCES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}
GRAPH = {
    name: {m for m in imports(path, set(SOURCES)) if m in SOURCES and m != name}
    for name, path in SOURCES.items()
}


@pytest.mark.parametrize("module", sorted(SOURCES))
def test_every_import_points_down_or_sideways(module):
    upward = [target for target in GRAPH[module] if floor(target) > floor(module)]
    assert not upward, f"{module} (floor {floor(module)}) imports {upward}"
    if floor(module) < FLOORS["study"]:
        external = {m.split(".")[0] for m in imports(SOURCES[module], set(SOURCES))}
        assert not external & set(STUDY_ONLY), f"{module} imports {external & set(STUDY_ONLY)}"


def test_no_modules_import_each_other_in_a_loop():
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        path.append(node)
        for target in sorted(GRAPH[node]):
            if state.get(target) == 1:
                loop = path[path.index(target) :] + [target]
                raise AssertionError("import loop: " + " -> ".join(loop))
            if target not in state:
                visit(target)
        path.pop()
        state[node] = 2

    for node in sorted(GRAPH):
        if node not in state:
            visit(node)


def test_importing_the_model_loads_no_allocator_solver_or_plotting_library():
    code = (
        "import sys, platoon_opt; "
        "loaded = [m for m in ('platoon_opt.solvers', 'platoon_opt.study', 'casadi', 'clarabel', 'osqp', "
        "'matplotlib', 'tqdm') if m in sys.modules]; "
        "assert not loaded, loaded"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
