"""The layout tells the architecture: a pure core, the I/O at the edges, no simulator in the flying code."""

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CORE = REPO / "auxgps" / "core"

#: What a core module may import: maths libraries, the standard library's pure parts, the core and its config.
CORE_ALLOWED = {"__future__", "numpy", "scipy", "cv2", "filterpy", "pymap3d", "dataclasses", "enum", "bisect",
                "collections", "logging", "typing", "auxgps.core", "auxgps.config", "auxgps.errors"}
#: Calls that read a clock, a device or the network.
CORE_FORBIDDEN_NAMES = {"VideoCapture", "perf_counter", "monotonic", "time", "sleep", "socket", "Thread", "open"}


def imports_of(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(node.module)
    return names


def test_core_modules_import_only_maths_and_the_core():
    for path in sorted(CORE.glob("*.py")):
        for name in imports_of(path):
            assert any(name == a or name.startswith(a + ".") for a in CORE_ALLOWED), f"{path.name} imports {name}"
    # The photo block (maps and orthophotos from photos) is core too: no file, clock or simulator in it.
    for path in sorted((REPO / "auxgps" / "photo").glob("*.py")):
        for name in imports_of(path):
            assert any(name == a or name.startswith(a + ".") for a in CORE_ALLOWED | {"auxgps.photo", "functools"}), \
                f"photo/{path.name} imports {name}"


def test_core_modules_read_no_clock_device_or_socket():
    for path in sorted(CORE.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
                assert name not in CORE_FORBIDDEN_NAMES, f"{path.name}:{node.lineno} calls {name}"


def test_the_flying_code_imports_no_simulator():
    code = ("import sys, auxgps.cli, auxgps.companion, auxgps.replay, auxgps.io.camera; "
            "print(','.join(m for m in sys.modules if m.startswith('auxgps.sim') or m.startswith('auxgps.evaluation')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"imported by auxgps run: {out}"


def test_one_place_builds_the_pipeline():
    """Only the estimator constructs the detector, mapper, localiser, filter and supervisor."""
    builders = {"FeatureDetector", "Mapper", "Localiser", "NavFilter", "Supervisor"}
    for path in sorted((REPO / "auxgps").rglob("*.py")):
        if path == CORE / "estimator.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                assert node.func.id not in builders, f"{path.relative_to(REPO)}:{node.lineno} builds a {node.func.id}"
