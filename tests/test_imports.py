"""The algorithms import without the simulator, the zoo or the plotting libraries; the collection loads when a
standard dataset must be made; the data package's modules import one way, each alone."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

#: What an algorithm import must not load: the tasks and their simulator, Minari, the zoo, Optuna, matplotlib.
HEAVY = ("pybullet", "envs", "minari", "rl_zoo3", "optuna", "matplotlib", "sb3_cql.data.collection")


def loaded_after(code: str) -> list[str]:
    """The :data:`HEAVY` modules loaded after ``code`` runs in a fresh interpreter."""
    check = f"{code}; import sys; print([name for name in {HEAVY!r} if name in sys.modules])"
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, check=True)
    return eval(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(
    "code",
    ["import sb3_cql", "from sb3_cql import CQL, BC", "from sb3_cql.common import OfflineSAC", "import sb3_cql.cql.policies"],
)
def test_the_algorithms_import_nothing_of_the_simulator_or_the_zoo(code):
    assert loaded_after(code) == []


def test_loading_data_imports_minari_but_not_the_simulator():
    assert loaded_after("from sb3_cql.data import fill_replay_buffer") == ["minari"]


def test_the_collection_is_imported_when_it_is_asked_for():
    loaded = loaded_after("from sb3_cql.data import ensure_dataset, standard_collection")
    assert {"pybullet", "envs", "sb3_cql.data.collection"} <= set(loaded)


def test_loading_data_and_writing_files_atomically_import_no_torch():
    code = "import sb3_cql.common.atomic, sb3_cql.protocol.records; from sb3_cql.data import load_dataset, fill_replay_buffer"
    check = f"{code}; import sys; print([name for name in ('torch', 'stable_baselines3') if name in sys.modules])"
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, check=True)
    assert result.stdout.strip().splitlines()[-1] == "[]"


# The data package: one role a module, imports running one way ----------------------------------------------------

DATA = Path(__file__).resolve().parents[1] / "sb3_cql" / "data"
#: The modules of the data package, by name (``sb3_cql.data`` for its ``__init__``).
DATA_MODULES = {
    "sb3_cql.data" if path.stem == "__init__" else f"sb3_cql.data.{path.stem}": path for path in sorted(DATA.glob("*.py"))
}


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, at module level or in a function: ``from A import B`` is ``A.B`` where that is a
    module of :data:`DATA_MODULES`, ``A`` otherwise (the package imports itself absolutely)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: a relative import"
            for alias in node.names:
                found.add(f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in DATA_MODULES else node.module)
    return found


def test_no_data_module_imports_one_that_imports_it_back():
    graph = {
        name: {module for module in imported_modules(path) if module in DATA_MODULES and module != name}
        for name, path in DATA_MODULES.items()
    }

    def reaches(start: str, goal: str) -> list[str] | None:
        stack, seen = [[start]], set()
        while stack:
            route = stack.pop()
            for module in graph[route[-1]]:
                if module == goal:
                    return [*route, module]
                if module not in seen:
                    seen.add(module)
                    stack.append([*route, module])
        return None

    circles = [route for name in graph for route in [reaches(name, name)] if route is not None]
    assert circles == [], "import circles: " + "; ".join(" -> ".join(route) for route in circles)


def test_the_data_package_imports_nothing_of_the_commands():
    commands = ("sb3_cql.evaluate", "sb3_cql.protocol", "sb3_cql.zoo")
    for name, path in DATA_MODULES.items():
        outside = {module for module in imported_modules(path) if module.startswith(commands)}
        assert not outside, f"{name} imports {outside}"


@pytest.mark.parametrize("module", sorted(DATA_MODULES))
def test_each_data_module_imports_alone(module):
    subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True, text=True, check=True)


# The package's parts: each imports only the parts below it ----------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
#: The package's parts from the bottom up (docs/development.md, *Layout*): each imports only parts of a lower layer.
LAYERS = [
    {"sb3_cql.files", "sb3_cql.processes", "sb3_cql.cluster"},
    {"envs"},
    {"sb3_cql.data"},
    {"sb3_cql.common"},
    {"sb3_cql.cql", "sb3_cql.iql", "sb3_cql.bc", "sb3_cql.callbacks"},
    {"sb3_cql.evaluate", "sb3_cql.zoo"},
    {"sb3_cql.protocol"},
    {"sb3_cql"},  # the package's door
]


def part_of(module: str) -> str:
    """The part of the package ``module`` belongs to: ``envs``, ``sb3_cql`` (its ``__init__``) or ``sb3_cql.X``."""
    words = module.split(".")
    return "envs" if words[0] == "envs" else ".".join(words[:2])


def test_each_part_of_the_package_imports_only_the_parts_below_it():
    layer = {part: level for level, parts in enumerate(LAYERS) for part in parts}
    files = [*ROOT.joinpath("sb3_cql").rglob("*.py"), *ROOT.joinpath("envs").rglob("*.py")]
    upward = []
    for path in files:
        relative = path.relative_to(ROOT).with_suffix("")
        source = part_of(".".join(relative.parts[:-1] if relative.name == "__init__" else relative.parts))
        assert source in layer, f"{path}: a part of the package not in LAYERS"
        for node in ast.walk(ast.parse(path.read_text())):
            names = [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            names += [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            for target in {part_of(name) for name in names if name.split(".")[0] in ("sb3_cql", "envs")}:
                if target != source and target != "sb3_cql" and layer[target] >= layer[source]:
                    upward.append(f"{relative} imports {target}")
    assert upward == [], "imports against the layers: " + "; ".join(upward)
