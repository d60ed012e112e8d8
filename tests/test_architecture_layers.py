"""The import graph keeps the layers of docs/architecture.md#layers: no module imports from a layer above it.

From the top: commands (scripts) -> bench -> analysis, integrations -> run folders (runs) -> the engine
(trainer, pipeline), evaluation and the method registry -> model, data, strategies, viewer -> rasterizer,
io (formats, config files included) -> cameras, schedule, callbacks, runtime (devices, ranks, threads),
kernels (compiled CPU kernels).
Every import counts, including those inside functions and under TYPE_CHECKING.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

import exploregs_plugin

PACKAGE = Path(exploregs_plugin.__file__).parent
LAYERS: list[tuple[str, ...]] = [
    ("scripts",),
    ("bench",),
    ("analysis", "integrations"),  # the research code states what to run; the bench runs it
    ("runs",),
    ("engine", "evaluation", "method_configs"),
    ("model", "data", "strategies", "viewer"),
    ("rasterizer", "io"),
    ("cameras", "schedule", "callbacks", "runtime", "kernels", ""),  # "" = the package's own __init__
]
LAYER_OF = {name: depth for depth, names in enumerate(LAYERS) for name in names}


def _module_name(path: Path, root: Path = PACKAGE.parent) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@functools.lru_cache(maxsize=None)
def _statements(path: Path) -> tuple[ast.stmt, ...]:
    """The import statements and class definitions of ``path``, at any depth (functions and
    ``if TYPE_CHECKING:`` included): the only nodes the checks below read. Parsed once per session:
    every check walks the same ~200 files, and parsing them is about a second of CPU each time."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return tuple(node for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom, ast.ClassDef)))


def _imports(path: Path) -> set[str]:
    """Every exploregs_plugin module ``path`` imports (absolute names)."""
    module = _module_name(path)
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found: set[str] = set()
    for node in _statements(path):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.add(name)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {name for name in found if name.split(".")[0] == "exploregs_plugin"}


def _unit(module: str) -> str:
    """The top-level unit of the package a module belongs to (``strategies``, ``trainer``, "")."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


@functools.lru_cache(maxsize=None)
def _graph() -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_unit_of_the_package_has_a_layer():
    units = {_unit(m) for m in _graph()}
    assert units - set(LAYER_OF) == set(), "put every new top-level module or package into LAYERS"
    assert set(LAYER_OF) - units == set(), "LAYERS names a unit that no longer exists"


def test_no_module_imports_from_a_layer_above_it():
    upward = []
    for module, imports in _graph().items():
        for target in imports:
            if LAYER_OF[_unit(target)] < LAYER_OF[_unit(module)]:
                upward.append(f"{module} -> {target}")
    assert upward == []


def test_the_checker_resolves_relative_and_function_level_imports():
    # seedsplit imports its siblings relatively; the bench worker imports the trainer inside a function
    assert "exploregs_plugin.strategies.exploration" in _imports(PACKAGE / "strategies" / "seedsplit.py")
    assert "exploregs_plugin.engine.trainer" in _imports(PACKAGE / "bench" / "worker.py")
    assert "exploregs_plugin.engine.pipeline" in _imports(PACKAGE / "analysis" / "tensorboard.py")  # TYPE_CHECKING


def test_io_knows_formats_only():
    # io may use the camera record and its own modules, nothing that renders or trains
    for module, imports in _graph().items():
        if _unit(module) == "io":
            assert {_unit(t) for t in imports} <= {"io", "cameras"}, (module, imports)


LAZY_IN_TRAINING = ("viser", "tensorboard", "torch.utils.tensorboard")
"""The viewer's server and tensorboard: they cost a quarter second and more at every start of eg-train,
a bench worker or eg-eval, so they load when a viewer or a writer is built."""
LAZY_IN_HELP = ("pycolmap", "viser", "exploregs_plugin.data.builtin.presets", "exploregs_plugin.data.process.run")
"""pycolmap, viser and the built-in scenes' generator: they load when a capture is read or posed, a page
written, a scene made, not when eg-train, eg-process or eg-export --help imports what it prints."""
IMPORT_PROBES = {
    "training": (("exploregs_plugin.scripts.train", "exploregs_plugin.bench.worker"), LAZY_IN_TRAINING),
    "help": (("exploregs_plugin.scripts.train", "exploregs_plugin.scripts.process", "exploregs_plugin.scripts.export"),
             LAZY_IN_HELP),
}
"""Probe name -> (the modules a fresh interpreter imports, the modules that must not load with them)."""


@pytest.fixture(scope="module")
def fresh_imports() -> dict[str, list[str]]:
    """Probe name -> the forbidden modules that loaded, in a fresh interpreter that imported the probe's
    modules. One interpreter for every probe: it imports the package and torch (what every probe
    pays for, about 2 s of CPU, loading none of the forbidden modules) and then forks a child per
    probe, so each probe's modules are imported into an interpreter that has seen only that much."""
    import json
    import subprocess
    import sys

    probe = f"""
import json, os, sys
import exploregs_plugin, torch  # the package first, as it imports itself
probes = {IMPORT_PROBES!r}
found = {{"before the probes": sorted(m for _, forbidden in probes.values() for m in forbidden if m in sys.modules)}}
for name, (modules, forbidden) in probes.items():
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: import, answer, and never run the rest of this script
        try:
            os.close(read)
            for module in modules:
                __import__(module)
            os.write(write, json.dumps(sorted(m for m in forbidden if m in sys.modules)).encode())
        except BaseException:
            import traceback
            traceback.print_exc()
            os._exit(1)
        os._exit(0)
    os.close(write)
    with os.fdopen(read) as answer:
        text = answer.read()
    _, status = os.waitpid(pid, 0)
    found[name] = json.loads(text) if status == 0 else f"the probe failed (exit status {{status}}), see stderr"
print(json.dumps(found))
"""
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    found = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(isinstance(v, list) for v in found.values()), (found, out.stderr[-2000:])
    assert found.pop("before the probes") == []  # the shared start loads none of what a probe looks for
    return found


def test_training_loads_the_viewer_and_tensorboard_only_when_used(fresh_imports):
    # the viewer's server (viser) and tensorboard cost a quarter second and more at every start of
    # eg-train, a bench worker or eg-eval; they load when a viewer or a writer is built
    assert fresh_imports["training"] == []


def test_the_commands_help_loads_no_reader_viewer_or_scene_generator(fresh_imports):
    # eg-train, eg-process and eg-export --help import what they print: pycolmap, viser and the
    # built-in scenes' generator load when a capture is read or posed, a page written, a scene made
    assert fresh_imports["help"] == []
    # and they still load where used: the lazy names resolve
    from exploregs_plugin import data
    from exploregs_plugin.data import process

    assert callable(data.parse_dataset) and "builtin:default" in {f"builtin:{k}" for k in data.PRESETS}
    assert callable(process.process_capture) and callable(process.is_posed)


def _module_imports(path: Path, modules: set[str], root: Path = PACKAGE.parent) -> set[str]:
    """The package's modules ``path`` imports: at module level, inside functions and under
    ``if TYPE_CHECKING:`` (a typing-only import still makes the two modules depend on each
    other); ``from pkg import sub`` names the submodule ``pkg.sub``."""
    module = _module_name(path, root)
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found: set[str] = set()
    for node in _statements(path):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - (node.level - 1)] if node.level else []
            name = ".".join(base + ([node.module] if node.module else []))
            subs = {f"{name}.{alias.name}" for alias in node.names} & modules
            found |= subs if len(subs) == len(node.names) else subs | {name}
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return (found & modules) - {module}


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected sets of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                found.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circle():
    # a circle makes import order matter and hides which part depends on which. A config that
    # builds its object imports it inside setup(), so the object must not import the config back,
    # not even for a type: the viewer reads ViewerSettings, and ViewerConfig(ViewerSettings).setup
    # builds it (viewer.config -> viewer.viewer -> viewer.settings)
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {_module_name(p) for p in paths}
    assert _circles({_module_name(p): _module_imports(p, modules) for p in paths}) == []
    # the checker sees a circle where there is one
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_the_circle_checker_counts_typing_only_imports(tmp_path):
    # the circle the viewer had: the config imports the object in setup(), the object imports
    # the config's type under TYPE_CHECKING
    package = tmp_path / "exploregs_plugin"
    package.mkdir()
    (package / "config.py").write_text("def setup():\n    from exploregs_plugin.obj import Obj\n")
    (package / "obj.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                    "    from exploregs_plugin.config import Config\n")
    paths = sorted(package.glob("*.py"))
    modules = {_module_name(p, tmp_path) for p in paths}
    graph = {_module_name(p, tmp_path): _module_imports(p, modules, tmp_path) for p in paths}
    assert _circles(graph) == [["exploregs_plugin.config", "exploregs_plugin.obj"]]


def test_no_two_classes_of_the_package_share_a_name():
    # one name, one class: a reader (or an import) never has to ask which SeedSplitStrategy is meant
    defined: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in _statements(path):
            if isinstance(node, ast.ClassDef):
                defined.setdefault(node.name, []).append(str(path.relative_to(PACKAGE)))
    assert {name: where for name, where in defined.items() if len(where) > 1} == {}
