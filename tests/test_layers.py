"""The layer rules of docs/architecture.md: imports go one way, by statement or by name (a
``"module:attribute"`` string, an ``import_module`` argument), and only the sim's worlds import
pybullet and mujoco, one module each."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tensegrity_gym", "estimation", "hardware", "agents")

# Which project packages each part may import (itself always allowed).
ALLOWED: dict[str, set[str]] = {
    "tensegrity_gym": set(),  # the package __init__: registration only
    "tensegrity_gym.model": set(),
    "tensegrity_gym.sim": {"tensegrity_gym.model"},
    "estimation": {"tensegrity_gym.model"},
    "hardware": {"tensegrity_gym.model"},
    "hardware.link.emulator": {"hardware", "tensegrity_gym.model", "tensegrity_gym.sim"},
    "tensegrity_gym.envs": {
        "tensegrity_gym.model", "tensegrity_gym.sim", "tensegrity_gym.tasks",
        "estimation", "hardware",
    },
    "tensegrity_gym.tasks": {
        "tensegrity_gym.model", "tensegrity_gym.sim", "estimation", "hardware",
    },
    "agents": {"tensegrity_gym", "estimation", "hardware"},
}  # fmt: skip


def _part(module: str) -> str:
    """The most specific key of ALLOWED that contains ``module``."""
    best = ""
    for key in ALLOWED:
        if (module == key or module.startswith(key + ".")) and len(key) > len(best):
            best = key
    return best


def _modules() -> list[tuple[str, Path]]:
    out = []
    for pkg in PACKAGES:
        for file in sorted((ROOT / pkg).rglob("*.py")):
            rel = file.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out.append((".".join(parts), file))
    return out


# A module named by a string: "package.module" or an entry point "package.module:attr".
_NAMED = re.compile(rf"^({'|'.join(PACKAGES)})(\.[A-Za-z_]\w*)*(:[A-Za-z_][\w.]*)?$")

# The registry's table names the built-in parts it makes on demand (that is its job:
# importing them would make importing the registry heavy); the package __init__ names
# the env's entry points for Gymnasium. Nothing else may name a module it may not import.
NAMED_ALLOWED: dict[str, set[str]] = {
    "tensegrity_gym": {"tensegrity_gym.envs"},
    "tensegrity_gym.model.registry": {"estimation", "tensegrity_gym.tasks"},
}


def _named(tree: ast.AST) -> list[str]:
    """The project modules string constants name (dotted, with a ``:`` entry point or
    not); a lone package name ("agents") is a word, not a module, and is left out."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            text = node.value.strip()
            if _NAMED.match(text) and ("." in text or ":" in text):
                names.append(text.partition(":")[0])
    return names


def _imports(file: Path, *, named: bool = True) -> list[str]:
    """What ``file`` imports by statement, and (``named``) by string."""
    tree = ast.parse(file.read_text())
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names + (_named(tree) if named else [])


MODULES = _modules()


def test_every_package_is_scanned() -> None:
    found = {name.split(".")[0] for name, _ in MODULES}
    assert found == set(PACKAGES)


@pytest.mark.parametrize(("module", "file"), MODULES, ids=[m for m, _ in MODULES])
def test_imports_go_one_way(module: str, file: Path) -> None:
    part = _part(module)
    assert part, f"{module} belongs to no layer"
    allowed = ALLOWED[part] | {part}
    for name in _imports(file):
        top = name.split(".")[0]
        if top not in PACKAGES:
            continue
        target = _part(name) or name
        if name in _named(ast.parse(file.read_text())) and any(
            target == a or target.startswith(a + ".") for a in NAMED_ALLOWED.get(module, ())
        ):
            continue
        if module == "tensegrity_gym" or target == "tensegrity_gym":
            # The package __init__ imports nothing of ours; others may import the
            # package itself (it only registers envs).
            assert module != "tensegrity_gym", f"tensegrity_gym/__init__ imports {name}"
            continue
        ok = any(target == a or target.startswith(a + ".") for a in allowed)
        assert ok, f"{module} ({part}) may not import {name} ({target})"


def test_only_the_sim_world_imports_pybullet() -> None:
    users = [
        m
        for m, f in MODULES
        if any(n.split(".")[0] == "pybullet" for n in _imports(f, named=False))
    ]
    assert users == ["tensegrity_gym.sim.world"]


def test_only_the_mujoco_world_imports_mujoco() -> None:
    users = [
        m for m, f in MODULES if any(n.split(".")[0] == "mujoco" for n in _imports(f, named=False))
    ]
    assert users == ["tensegrity_gym.sim.mujoco_world"]


def test_nothing_imports_agents() -> None:
    for module, file in MODULES:
        if module.startswith("agents"):
            continue
        assert not any(n.split(".")[0] == "agents" for n in _imports(file)), module


def test_a_wrong_way_import_is_caught(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("from tensegrity_gym.sim.world import PhysicsWorld\n")
    name = _imports(bad)[0]
    assert _part(name) not in ALLOWED["estimation"] | {"estimation"}


@pytest.mark.parametrize(
    "source",
    [
        'RUN = "agents.recordings.calibrate:calibrate_command"\n',
        'import importlib\nmodule = importlib.import_module("agents.training.train")\n',
    ],
)
def test_a_wrong_way_string_import_is_caught(tmp_path: Path, source: str) -> None:
    """A lower layer naming a higher one by string fails the layer test: the file is
    checked as if it were ``tensegrity_gym/envs/calibration.py``."""
    bad = tmp_path / "calibration.py"
    bad.write_text(source)
    with pytest.raises(AssertionError, match="may not import agents"):
        test_imports_go_one_way("tensegrity_gym.envs.calibration", bad)
    assert _named(ast.parse("x = 'agents'\ny = 'see agents.cli'\n")) == []


def test_nothing_but_the_command_line_imports_the_benchmarks() -> None:
    """Training, evaluation and recording never pull the benchmarks in."""
    for module, file in MODULES:
        if module.startswith(("agents.benchmarks", "agents.cli")):
            continue
        names = _imports(file)
        assert not any(n.startswith("agents.benchmarks") for n in names), module


def _import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports, function-level imports included.
    ``from a.b import c`` names the module ``a.b.c`` when there is one, else ``a.b``."""
    known = {m for m, _ in MODULES}
    graph: dict[str, set[str]] = {}
    for module, file in MODULES:
        targets: set[str] = set()
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names if a.name in known}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                subs = {f"{node.module}.{a.name}" for a in node.names} & known
                targets |= subs or ({node.module} & known)
        graph[module] = targets - {module}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_anywhere() -> None:
    """Not between packages, not inside one, not behind a function-level import."""
    assert _cycles(_import_graph()) == []


def test_a_cycle_is_caught() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
