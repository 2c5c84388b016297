"""Every line of code knows its room: planners/ thinks without devices, simulators or networks;
drivers/ and sim/ never reach into planners/."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {
    "planners": {"pybullet", "pybullet_data", "franky", "franky_sim", "zenoh", "rerun", "pyrealsense2",
                 "open3d", "drivers", "sim", "cellctl"},
    "drivers": {"planners", "cellctl", "sim"},
    "sim": {"planners", "cellctl"},
}


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module


@pytest.mark.parametrize("room", sorted(FORBIDDEN))
def test_room_imports(room):
    bad = []
    for f in sorted((ROOT / room).rglob("*.py")):
        for line, mod in _imports(f):
            if mod.split(".")[0] in FORBIDDEN[room]:
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)
