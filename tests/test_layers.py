"""The package's layers, read from the imports of every module (ast), the way a reviewer would.

Layers, bottom up (a module imports only layers below its own; modules of one subpackage may
import each other)::

    0  probegrid.errors, probegrid._types, probegrid._version
    1  probegrid._fs, probegrid._jit, probegrid._machine
    2  probegrid.core
    3  probegrid.imageio | probegrid.scene | probegrid.store | probegrid.raytrace | probegrid.export
       | probegrid.usercache
    4  probegrid.bake | probegrid.filter
    5  probegrid.query (maps at a point trace a probe there with the bake's estimator)
    6  probegrid.jobs | service
    7  probegrid.cli | probegrid.client
    8  probegrid (the package's face: nothing imports it)

and, on top of the ranks: ``probegrid.client`` imports only errors, option types, the version,
core and the store's manifest models; ``service`` only the foundation, core, imageio, export (file formats), raytrace, the
per-machine cache, store and query; nothing in ``probegrid`` imports ``service`` but the ``serve`` command's one lazy import;
``probegrid.core`` imports numpy (and threadpoolctl, to bound BLAS threads) and no module that
reads or writes files, sockets, settings or the web.

Every import counts: module level, inside functions (lazy) and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
import functools
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

RANKS: dict[str, int] = {
    "probegrid.errors": 0, "probegrid._types": 0, "probegrid._version": 0,
    "probegrid._fs": 1, "probegrid._jit": 1, "probegrid._machine": 1,
    "probegrid.core": 2,
    "probegrid.imageio": 3, "probegrid.scene": 3, "probegrid.store": 3, "probegrid.raytrace": 3,
    "probegrid.export": 3, "probegrid.usercache": 3,
    "probegrid.bake": 4, "probegrid.filter": 4,
    "probegrid.query": 5,
    "probegrid.jobs": 6, "service": 6,
    "probegrid.cli": 7, "probegrid.client": 7,
    "probegrid": 8,
}
SUBPACKAGES = ("core", "scene", "store", "raytrace", "bake", "filter", "jobs", "export")
CLIENT_MAY_IMPORT = ("probegrid.errors", "probegrid._types", "probegrid._version",
                     "probegrid.core", "probegrid.store.manifest")
SERVICE_MAY_IMPORT = ("probegrid.errors", "probegrid._types", "probegrid._version",
                      "probegrid._fs", "probegrid.core", "probegrid.imageio", "probegrid.store",
                      "probegrid.raytrace", "probegrid.export", "probegrid.usercache",
                      "probegrid.query", "service")
#: The one import of the HTTP layer from the library: ``probegrid serve`` starts it.
SERVICE_FROM_LIBRARY = {("probegrid.cli", "service.main")}
CORE_THIRD_PARTY = {"numpy", "threadpoolctl"}
CORE_FORBIDDEN_STDLIB = {"os", "io", "sys", "pathlib", "shutil", "tempfile", "socket", "http",
                         "urllib", "json", "subprocess", "pickle", "sqlite3", "asyncio",
                         "fcntl", "mmap", "glob"}


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def room(module: str) -> str:
    """The layer unit of a module: its subpackage, or the top-level module itself."""
    parts = module.split(".")
    if parts[0] == "service":
        return "service"
    if len(parts) >= 2 and parts[1] in SUBPACKAGES:
        return ".".join(parts[:2])
    return ".".join(parts[:2])


@functools.lru_cache(maxsize=None)
def _raw_imports(text: str, package: str) -> tuple[tuple[int, str, tuple[str, ...]], ...]:
    """``(line, module, names)`` of every import in a module's text (``names`` empty for a plain
    ``import``), parsed once per text: the planted copies share every other file's parse."""
    found = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name, ()) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.append((node.lineno, target, tuple(alias.name for alias in node.names)))
    return tuple(found)


def imports(path: Path, module: str, root: Path) -> Iterator[tuple[int, str]]:
    """``(line, imported module)`` for every import of ``path`` (all levels of nesting)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for line, target, names in _raw_imports(path.read_text(encoding="utf-8"), package):
        if not names:
            yield line, target
        for name in names:  # `from pkg import submodule` imports the submodule
            sub = f"{target}.{name}"
            candidate = root.joinpath(*sub.split("."))
            if candidate.with_suffix(".py").is_file() or (candidate / "__init__.py").is_file():
                yield line, sub
            else:
                yield line, target


def violations(root: Path) -> list[str]:
    """Every import of ``root/probegrid`` and ``root/service`` that breaks the layers."""
    found = []
    files = sorted((root / "probegrid").rglob("*.py")) + sorted((root / "service").rglob("*.py"))
    for path in files:
        module = module_name(path, root)
        here = room(module)
        for line, target in imports(path, module, root):
            top = target.split(".")[0]
            where = f"{path.relative_to(root)}:{line} imports {target}"
            impure = top in CORE_FORBIDDEN_STDLIB or (
                top not in sys.stdlib_module_names and top not in CORE_THIRD_PARTY)
            if here == "probegrid.core" and top not in ("probegrid", "__future__") and impure:
                found.append(f"{where}: probegrid.core is pure math (numpy only, no I/O)")
            if top not in ("probegrid", "service"):
                continue
            there = room(target)
            if here.startswith("probegrid") and there == "service":
                if (room(module), target) not in SERVICE_FROM_LIBRARY:
                    found.append(f"{where}: the library never imports the HTTP layer")
                continue
            if target == "probegrid":
                found.append(f"{where}: nothing imports the package's face; import the module")
                continue
            if here == there:
                continue
            if RANKS[there] >= RANKS[here]:
                kind = "sideways" if RANKS[there] == RANKS[here] else "upward"
                found.append(f"{where}: {kind} import ({here} is layer {RANKS[here]}, "
                             f"{there} layer {RANKS[there]})")
            elif here == "probegrid.client" and not target.startswith(CLIENT_MAY_IMPORT):
                found.append(f"{where}: the client imports only core types and manifest models")
            elif here == "service" and not target.startswith(SERVICE_MAY_IMPORT):
                found.append(f"{where}: the service imports only core, imageio, store and query")
    return found


def room_graph(root: Path) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for path in sorted((root / "probegrid").rglob("*.py")) + sorted((root / "service").rglob("*.py")):
        module = module_name(path, root)
        edges = graph.setdefault(room(module), set())
        for _, target in imports(path, module, root):
            if target.split(".")[0] in ("probegrid", "service") and room(target) != room(module):
                edges.add(room(target))
    return graph


def depth(graph: dict[str, set[str]]) -> int:
    """Levels of the room graph (a room with no import is level 1); raises on a cycle."""
    memo: dict[str, int] = {}

    def level(node: str, path: tuple[str, ...]) -> int:
        if node in path:
            raise AssertionError(f"import cycle: {' -> '.join(path + (node,))}")
        if node not in memo:
            memo[node] = 1 + max((level(n, path + (node,)) for n in graph.get(node, ())),
                                 default=0)
        return memo[node]

    return max(level(n, ()) for n in graph)


def test_every_import_goes_down_the_layers():
    assert violations(REPO) == []


def test_every_module_has_a_layer():
    for path in (REPO / "probegrid").rglob("*.py"):
        assert room(module_name(path, REPO)) in RANKS, path


def test_the_layer_graph_has_no_cycle_and_at_most_seven_levels():
    graph = room_graph(REPO)
    graph.pop("probegrid", None)  # the face re-exports; nothing imports it
    assert depth(graph) <= 7


@pytest.mark.parametrize("plant, expect", [
    ("probegrid/core/sh/projection.py", "upward import (probegrid.core is layer 2, probegrid.bake layer 4)"),
    ("probegrid/store/reader.py", "sideways import (probegrid.store is layer 3, probegrid.scene"),
    ("probegrid/_jit.py", "upward import"),
])
def test_a_planted_upward_or_sideways_import_is_named(tmp_path, plant, expect):
    for part in ("probegrid", "service"):
        shutil.copytree(REPO / part, tmp_path / part,
                        ignore=shutil.ignore_patterns("__pycache__", "static"))
    target = "probegrid.bake.driver" if "core" in plant or "_jit" in plant else "probegrid.scene"
    file = tmp_path / plant
    file.write_text(file.read_text() + f"\n\ndef _planted():\n    import {target}\n")
    found = violations(tmp_path)
    assert len(found) == 1 and plant in found[0] and expect in found[0], found


def test_core_with_file_io_or_the_service_importing_the_baker_is_named(tmp_path):
    for part in ("probegrid", "service"):
        shutil.copytree(REPO / part, tmp_path / part,
                        ignore=shutil.ignore_patterns("__pycache__", "static"))
    (tmp_path / "probegrid/core/dfg.py").write_text(
        (tmp_path / "probegrid/core/dfg.py").read_text() + "\nimport pathlib\n")
    (tmp_path / "service/deps.py").write_text(
        (tmp_path / "service/deps.py").read_text() + "\nfrom probegrid.bake import settings\n")
    found = violations(tmp_path)
    assert any("core/dfg.py" in f and "no I/O" in f for f in found), found
    assert any("service/deps.py" in f and "imports only core" in f for f in found), found


def test_the_package_face_hands_on_its_public_names():
    """httpx's habit: the names the README shows are reachable from the package itself."""
    import probegrid
    from probegrid.bake import bake
    from probegrid.core import sh
    from probegrid.core.grid import GridSpec
    from probegrid.filter import FilterSettings, filter_environment
    from probegrid.query import ProbeField

    assert probegrid.__all__ == sorted(probegrid.__all__)
    assert set(probegrid.__all__) == {
        "BakeSettings", "CubeMap", "FilterSettings", "GridSpec", "LocalExecutor", "ProbeField",
        "ProbegridError",
        "__version__", "diffuse", "filter_environment", "imageio", "layouts", "load_gltf",
        "open_store", "sh", "specular"}
    for name in probegrid.__all__:
        assert getattr(probegrid, name) is not None
    assert probegrid.GridSpec is GridSpec and probegrid.ProbeField is ProbeField
    assert probegrid.bake.bake is bake and probegrid.sh is sh
    assert probegrid.FilterSettings is FilterSettings
    assert probegrid.filter_environment is filter_environment
    with pytest.raises(AttributeError):
        probegrid.interpolate  # noqa: B018 (no such module at the top)
