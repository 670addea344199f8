"""The package's layers import downward only, and no modules import each other in a circle.

Layers, bottom up (DESIGN.md, house style): the top-level helper modules (pig.config, pig._io, pig._outputs,
pig._cli, pig.progress, ...); body, field, data, metrics, render; avatar; the browser viewer (pig.viewer); stages
and pig.doctor (which checks what they need); the `pig` command (pig.cli, pig.__main__). Every import counts, at
module level or inside a function, read from the source by `ast` (no module is imported here).
"""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pig"
LAYERS = {"body": 1, "field": 1, "data": 1, "metrics": 1, "render": 1, "avatar": 2, "viewer": 3, "stages": 4, "doctor": 4,
          "cli": 5, "__main__": 5}


def modules() -> dict[str, Path]:
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def layer(module: str) -> int:
    parts = module.split(".")
    return LAYERS.get(parts[1], 0) if len(parts) > 1 else 0


def imported(module: str, path: Path, known: dict[str, Path]) -> dict[str, int]:
    """{pig module imported by `module`: line} (a `from X import name` of a submodule counts that submodule)."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = {}
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([base] if base else []))
            names = [base] + [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for name in names:
            while name and name not in known:  # pig.render.RasterizerConfig -> pig.render
                name = name.rpartition(".")[0]
            if name.startswith("pig") and name != module:
                found.setdefault(name, node.lineno)
    return found


def import_graph() -> dict[str, dict[str, int]]:
    known = modules()
    return {module: imported(module, path, known) for module, path in known.items()}


def test_the_walk_sees_imports_at_every_depth_and_relative_ones():
    graph = import_graph()
    assert "pig._io" in graph["pig.body.params"]  # module level
    assert "pig.avatar.checkpoint" in graph["pig.avatar.export"]  # inside a function
    assert "pig.body.npz" in graph["pig.body.motion"]  # `from .npz import read_npz`
    assert len(graph) > 60


def test_no_module_imports_from_a_layer_above_it():
    graph = import_graph()
    upward = [f"{module} (layer {layer(module)}) imports {target} (layer {layer(target)}), line {line}"
              for module, targets in graph.items() for target, line in targets.items() if layer(target) > layer(module)]
    assert not upward, "\n".join(upward)


def test_no_import_circle():
    graph = import_graph()
    visiting, done, circles = [], set(), []

    def visit(module):
        visiting.append(module)
        for target in graph[module]:
            if target in visiting:
                circles.append(visiting[visiting.index(target):] + [target])
            elif target not in done:
                visit(target)
        visiting.pop()
        done.add(module)

    for module in graph:
        if module not in done:
            visit(module)
    assert not circles, "\n".join(" -> ".join(circle) for circle in circles)


@pytest.mark.parametrize("stage_helper", ["_io", "_outputs", "_cli"])
def test_the_shared_helpers_sit_at_the_bottom(stage_helper):
    assert (PACKAGE / f"{stage_helper}.py").is_file() and not (PACKAGE / "stages" / f"{stage_helper}.py").exists()
    assert layer(f"pig.{stage_helper}") == 0
