"""The house as issue 20 fixed it, read from the source with `ast` (no import runs):

* imports point downward only: apparatus -> posterior -> envs -> agents -> (config, runs) ->
  (evaluation, league, deploy, training, adaptation) -> cli, with the bottom modules (yaml_io,
  checkpoints, metrics, overlays, transitions) below all of them; an import inside a function
  counts as much as one at the top;
* no circle between modules;
* no room in alignrl/ over about 600 lines;
* no learner-specific branch (`isinstance(..., SAC)`, `algorithm == "sac"`) outside the
  learners themselves (alignrl/agents/).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "alignrl"
MAX_LINES = 620  # "about 600"

# A module's layer is that of the first prefix found here (longest first); it may import
# its own layer and those below, never above.
LAYERS = {
    "alignrl": 0,
    "alignrl.yaml_io": 0,
    "alignrl.checkpoints": 0,
    "alignrl.metrics": 0,
    "alignrl.overlays": 0,
    "alignrl.intervals": 0,
    "alignrl.animation": 0,  # frames and GIFs of an alignment: numpy, matplotlib, Pillow
    "alignrl.transitions": 0,  # the Transition record envs fill and learners store: numpy only
    "alignrl.apparatus": 1,
    "alignrl.posterior": 2,  # inference about a column from its readings (design.md)
    "alignrl.envs": 3,
    "alignrl.agents": 4,
    "alignrl.plots": 4,
    "alignrl.config_reading": 0,  # how a config file is read: bounded YAML, strict models
    "alignrl.config": 5,  # the experiment models: they build tasks, limits and learners
    "alignrl.runs": 5,
    "alignrl.evaluation": 6,
    "alignrl.league": 6,
    "alignrl.deploy": 6,
    "alignrl.training": 6,
    "alignrl.adaptation": 6,
    "alignrl.api": 6,  # train, evaluate, align from Python (docs/python.md)
    "alignrl.cli": 7,
    "alignrl.__main__": 7,  # `python -m alignrl`: the command itself
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def layer(module: str) -> int:
    for prefix in sorted(LAYERS, key=len, reverse=True):
        if module == prefix or module.startswith(prefix + "."):
            return LAYERS[prefix]
    raise AssertionError(f"{module}: no layer in tests/test_structure.py LAYERS")


def imports_of(module: str) -> set[str]:
    """The alignrl modules `module` imports, wherever the import stands."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            # `from alignrl.x import y`: y may be a module of its own
            names = [f"{base}.{alias.name}" for alias in node.names] + [base]
        for name in names:
            while name and name not in MODULES:
                name = name.rpartition(".")[0]
            if name and name != module and name.startswith("alignrl"):
                found.add(name)
    # A module's package __init__ runs on import, but importing one's own package is no arrow.
    return {name for name in found if not module.startswith(name + ".")}


GRAPH = {module: imports_of(module) for module in MODULES}


def test_every_import_points_down_or_sideways() -> None:
    upward = [
        f"{module} (layer {layer(module)}) imports {target} (layer {layer(target)})"
        for module, targets in GRAPH.items()
        for target in sorted(targets)
        if layer(target) > layer(module)
    ]
    assert not upward, "upward imports:\n" + "\n".join(upward)


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_import_circle() -> None:
    # A package's __init__ re-exporting its modules is no circle of the house: leave it out.
    graph = {
        module: {t for t in targets if MODULES[t].name != "__init__.py"}
        for module, targets in GRAPH.items()
    }
    circles = _circles(graph)
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_the_circle_finder_finds_a_circle() -> None:
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_no_room_over_about_600_lines() -> None:
    sizes = {module: len(path.read_text().splitlines()) for module, path in MODULES.items()}
    large = [
        f"{module}: {lines} lines" for module, lines in sorted(sizes.items()) if lines > MAX_LINES
    ]
    assert not large, "rooms over about 600 lines:\n" + "\n".join(large)


LEARNER_BRANCH = re.compile(
    r"isinstance\([^)]*\b(SAC|PPO)\b\)|algorithm\s*[!=]=\s*[\"'](sac|ppo)[\"']"
)


def test_no_learner_branch_outside_the_learners() -> None:
    found = [
        f"{path.relative_to(PACKAGE.parent)}:{number}: {line.strip()}"
        for module, path in MODULES.items()
        if not module.startswith("alignrl.agents")
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if LEARNER_BRANCH.search(line)
    ]
    assert not found, "learner-specific branches:\n" + "\n".join(found)
