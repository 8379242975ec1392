"""The package's layers, read from the source with ``ast``: no module imports a module of a
higher layer, no import cycles, and only :mod:`mmpc.highway` touches highway-env and pygame.

Imports inside functions count (a lazy upward import is still an upward dependency).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Source folder -> the installed package it becomes (pyproject.toml's package-dir).
PACKAGES = {"mmpc": "mmpc", "rl": "mmpc.rl", "imitation": "mmpc.imitation", "configs": "mmpc.configs"}

#: Layers, lowest first: (name, module prefixes). A module belongs to the layer of its longest
#: matching prefix; everything else under ``mmpc`` is the solver core.
LAYERS = (
    ("configs", ("mmpc.configs",)),
    ("core", ("mmpc",)),
    ("sim", ("mmpc.sim",)),
    ("verify", ("mmpc.verify",)),
    ("drivers", ("mmpc.drivers",)),
    ("highway", ("mmpc.highway",)),
    ("evaluate", ("mmpc.evaluate",)),
    ("applications", ("mmpc.rl", "mmpc.imitation")),
    ("cli", ("mmpc.cli", "mmpc.rl.cli", "mmpc.imitation.cli")),
)
#: Third-party packages only some layers may import: name -> the module prefixes allowed to.
RESTRICTED = {
    "highway_env": ("mmpc.highway",),
    "pygame": ("mmpc.highway",),
    "gymnasium": ("mmpc.highway", "mmpc.rl", "mmpc.imitation"),
    "stable_baselines3": ("mmpc.rl", "mmpc.imitation"),
}


def read_sources(root: Path = ROOT) -> dict[str, str]:
    """Module name -> source of every module of the installed packages."""
    sources = {}
    for folder, package in PACKAGES.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = path.relative_to(root / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            sources[".".join((package, *parts))] = path.read_text(encoding="utf-8")
    return sources


def _is_package(module: str, sources: dict[str, str]) -> bool:
    return any(other.startswith(module + ".") for other in sources)


def imports_of(module: str, source: str, sources: dict[str, str]) -> set[str]:
    """Modules ``module`` imports: mmpc's own (resolved to modules of ``sources``) and the
    top-level names of third-party packages."""
    found: set[str] = set()
    package = module if _is_package(module, sources) else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            # ``from package import submodule`` imports the submodule
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in sources else base for alias in node.names]
        else:
            continue
        for name in names:
            if name.split(".")[0] != "mmpc":
                found.add(name.split(".")[0])
                continue
            while name not in sources and "." in name:  # ``import mmpc.x.y`` of a function or class: its module
                name = name.rpartition(".")[0]
            if name != module:
                found.add(name)
    return found


def layer_of(module: str) -> int:
    best, index = -1, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, index = len(prefix), i
    return index


def _allowed(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
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


def layer_violations(sources: dict[str, str]) -> list[str]:
    """Every upward import, import cycle and restricted third-party import, as messages."""
    graph = {module: imports_of(module, source, sources) for module, source in sources.items()}
    problems = []
    for module, targets in sorted(graph.items()):
        for target in sorted(targets):
            if target in sources:
                if layer_of(target) > layer_of(module):
                    problems.append(f"{module} ({LAYERS[layer_of(module)][0]}) imports {target} "
                                    f"({LAYERS[layer_of(target)][0]}), a higher layer")
            elif target in RESTRICTED and not _allowed(module, RESTRICTED[target]):
                problems.append(f"{module} imports {target}; only {RESTRICTED[target]} may")
    internal = {module: {t for t in targets if t in sources} for module, targets in graph.items()}
    problems += [f"import cycle: {' -> '.join(component)}" for component in _cycles(internal)]
    return problems


def test_the_tree_respects_its_layers():
    sources = read_sources()
    assert {"mmpc.solver.optimizer", "mmpc.solver.iterations", "mmpc.drivers.base", "mmpc.highway.runner", "mmpc.evaluate.backends", "mmpc.cli.main",
            "mmpc.rl.envs", "mmpc.imitation.dagger"} <= set(sources)
    assert layer_violations(sources) == []


@pytest.mark.parametrize("module,planted,expected", [
    ("mmpc.solver.optimizer", "from mmpc.highway import run_lockstep", "mmpc.solver.optimizer (core) imports mmpc.highway"),
    ("mmpc.config", "from mmpc.solver.config import OptimizerConfig", "import cycle:"),  # the solver reads the loader
    ("mmpc.mpc", "def f():\n    import mmpc.evaluate.store", "mmpc.mpc (core) imports mmpc.evaluate.store"),
    ("mmpc.drivers.frenet", "from mmpc.imitation.policy import PolicyDriver", "imports mmpc.imitation.policy"),
    ("mmpc.evaluate.tasks", "from mmpc.cli.arguments import seed_list", "imports mmpc.cli.arguments"),
    ("mmpc.ranking", "import gymnasium", "mmpc.ranking imports gymnasium"),
    ("mmpc.rl.envs", "from highway_env.envs.common.observation import KinematicObservation",
     "mmpc.rl.envs imports highway_env"),
    ("mmpc.problem", "from mmpc.mpc import MPC", "import cycle:"),
])
def test_a_planted_import_is_reported(module, planted, expected):
    sources = read_sources()
    sources[module] += "\n" + planted + "\n"
    problems = layer_violations(sources)
    assert any(expected in problem for problem in problems), problems


#: The most lines a module of the installed packages may have (a longer one holds two jobs).
MAX_MODULE_LINES = 700


def private_imports(sources: dict[str, str]) -> list[str]:
    """``from mmpc.x import _name`` lines: a private name used outside its module."""
    found = []
    for module, source in sources.items():
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").split(".")[0] == "mmpc"):
                found += [f"{module}:{node.lineno} imports {alias.name} from {node.module}" for alias in node.names
                          if alias.name.startswith("_") and not alias.name.startswith("__")]
    return found


def test_no_module_is_over_the_line_limit_and_no_private_name_crosses_a_module():
    sources = read_sources()
    long = {module: source.count("\n") for module, source in sources.items() if source.count("\n") > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"
    for folder in ("scripts", "tests"):  # the benchmarks and tests use the public names too
        for path in sorted((ROOT / folder).rglob("*.py")):
            sources[f"{folder}/{path.name}"] = path.read_text(encoding="utf-8")
    assert private_imports(sources) == []
    assert private_imports({"mmpc.x": "from mmpc.solver.execution import _SIMD_BYTES\n"}) == [
        "mmpc.x:1 imports _SIMD_BYTES from mmpc.solver.execution"]
