"""Every line of code knows its room: planners/ thinks without devices, simulators or networks;
drivers/ and sim/ never reach into planners/.

Inside cellctl/ the rooms are cellctl/scan/ (the scan-drawing job, no network), cellctl/service/ (the Zenoh
job service), cellctl/bench/ (the benchmarks) and cellctl/commissioning/ (doctor, hand-eye), with cli.py
and config.py beside them, and cellctl/tablet/ (the operator's web app, a Zenoh client like any other): scan/
imports nothing from cellctl.service, cellctl.bench, cellctl.commissioning, cellctl.tablet nor zenoh;
service/ nothing from cellctl.bench, cellctl.commissioning nor cellctl.tablet; commissioning/ nothing from
cellctl.service, cellctl.bench nor cellctl.tablet; tablet/ only the API and its client (no scan, no
devices, no simulator); and nothing in cellctl/ outside bench/ imports cellctl.bench but
cellctl/cli.py. Every import counts: absolute or relative, at the top of a module or inside a function."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {
    "planners": {"pybullet", "pybullet_data", "franky", "franky_sim", "zenoh", "rerun", "pyrealsense2",
                 "open3d", "drivers", "sim", "cellctl"},
    "drivers": {"planners", "cellctl", "sim"},
    "sim": {"planners", "cellctl"},
}
# room inside cellctl/ -> modules (and their submodules) it must not import
INNER = {
    "cellctl/scan": ("cellctl.service", "cellctl.bench", "cellctl.commissioning", "cellctl.tablet", "zenoh"),
    "cellctl/service": ("cellctl.bench", "cellctl.commissioning", "cellctl.tablet"),
    "cellctl/commissioning": ("cellctl.service", "cellctl.bench", "cellctl.tablet"),
    # a client like any other: the API and its client, nothing of the cell's own machinery or devices
    "cellctl/tablet": ("cellctl.scan", "cellctl.bench", "cellctl.commissioning", "cellctl.config",
                       "cellctl.service.server", "cellctl.service.worker", "cellctl.service.store", "drivers", "sim",
                       "pybullet", "open3d"),
}
BENCH_IMPORTERS = {"cellctl/cli.py"}  # the only files outside cellctl/bench/ that may import cellctl.bench


def _package(path: Path) -> str:
    """The package a file's relative imports start from: cellctl/scan/job.py and cellctl/scan/__init__.py
    -> cellctl.scan."""
    return ".".join(path.relative_to(ROOT).parent.parts)


def _imports(path: Path, package: str | None = None):
    """(line, dotted module) for every import in the file, relative ones resolved against ``package``.
    ``from a import b`` yields both a and a.b, since b may be a module (``from cellctl import bench``)."""
    package = _package(path) if package is None else package
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1])
                module = ".".join(p for p in (base, node.module) if p)
            else:
                module = node.module
            if not module:
                continue
            yield node.lineno, module
            for a in node.names:
                if a.name != "*":
                    yield node.lineno, f"{module}.{a.name}"


def _is_within(module: str, forbidden: str) -> bool:
    return module == forbidden or module.startswith(forbidden + ".")


def _files(room: str) -> list[Path]:
    files = sorted((ROOT / room).rglob("*.py"))
    assert files, f"{room}/ holds no Python files: was the room moved without this test?"
    return files


@pytest.mark.parametrize("room", sorted(FORBIDDEN))
def test_room_imports(room):
    bad = []
    for f in _files(room):
        for line, mod in _imports(f):
            if mod.split(".")[0] in FORBIDDEN[room]:
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("room", sorted(INNER))
def test_cellctl_inner_room_imports(room):
    bad = []
    for f in _files(room):
        for line, mod in _imports(f):
            if any(_is_within(mod, x) for x in INNER[room]):
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "\n".join(sorted(set(bad)))


def test_only_the_cli_imports_the_benches():
    bad = []
    for f in _files("cellctl"):
        rel = f.relative_to(ROOT).as_posix()
        if rel.startswith("cellctl/bench/") or rel in BENCH_IMPORTERS:
            continue
        for line, mod in _imports(f):
            if _is_within(mod, "cellctl.bench"):
                bad.append(f"{rel}:{line} imports {mod}")
    assert not bad, "\n".join(sorted(set(bad)))


def test_imports_are_found_relative_and_inside_functions(tmp_path):
    """The checker itself: relative imports resolve against the file's package, and an import inside a
    function counts as much as one at the top."""
    src = tmp_path / "job.py"
    src.write_text("from __future__ import annotations\n"
                   "from . import devices\n"
                   "from ..service.api import Keys\n"
                   "def f():\n"
                   "    from .. import bench\n"
                   "    import zenoh\n")
    found = {mod for _, mod in _imports(src, "cellctl.scan")}
    assert {"cellctl.scan.devices", "cellctl.service.api", "cellctl.service.api.Keys", "cellctl.bench",
            "zenoh"} <= found
    assert _is_within("cellctl.bench.scans", "cellctl.bench") and not _is_within("cellctl.benchmarks", "cellctl.bench")


def test_every_module_names_the_tests_that_test_it():
    """A newcomer finds the tests of a module with ``grep -l <dotted.module> tests/``: every module of the
    project is imported, or named in a docstring, by at least one test file (tests/README.md tells the way)."""
    tests = sorted((ROOT / "tests").glob("*.py"))
    text = "\n".join(p.read_text() for p in tests)
    imported = {m for p in tests for _, m in _imports(p, "tests")}
    unnamed = []
    for room in ("cellctl", "planners", "drivers", "sim", "configs"):
        for path in sorted((ROOT / room).rglob("*.py")):
            dotted = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            if path.name != "__init__.py" and dotted not in imported and dotted not in text:
                unnamed.append(dotted)
    assert not unnamed, f"no test file imports or names {unnamed}"
    listed = re.findall(r"\b(?:cellctl|planners|drivers|sim|configs)(?:\.\w+)+", " ".join(
        re.findall(r"Tests of: ([^\n]+(?:\n[^\n]+)*?)\.\n", text)))
    stale = [m for m in listed if not (ROOT / (m.replace(".", "/") + ".py")).is_file()
             and not (ROOT / m.replace(".", "/") / "__init__.py").is_file()]
    assert not stale, f"'Tests of:' names modules that do not exist: {stale}"
