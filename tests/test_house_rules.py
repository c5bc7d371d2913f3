"""The house rules as checks (`make lint` runs the same two): ruff on the whole tree, and the import contracts in
pyproject.toml ([tool.importlinter]: the layers, spine < stages in pipeline order < the simulated rig < the
application, every module in one; and the stages' rooms, entered only through a package's __init__), checked by
tools/lint_imports.py on a copy laid out as installed. Nothing is written to the repo."""
from __future__ import annotations

import ast
import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LINT_IMPORTS = REPO / "tools" / "lint_imports.py"
SOURCE_FOLDERS = ("odsplat", "acquisition", "sync", "processing", "reconstruction", "analysis", "hil_sim")

LAYERS = "layers: application > simulated rig > stages in pipeline order > spine"
APP = "the application (odsplat.app) uses only the stages' __init__"

needs_ruff = pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed")
needs_import_linter = pytest.mark.skipif(importlib.util.find_spec("importlinter") is None,
                                         reason="import-linter is not installed")


def _lint_imports(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(LINT_IMPORTS), "--root", str(root), "--no-logo"],
                          capture_output=True, text=True, timeout=120)


@needs_ruff
def test_ruff_passes_on_the_tree():
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", "."],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@needs_import_linter
def test_import_contracts_are_kept():
    proc = _lint_imports(REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


@pytest.fixture
def tree(tmp_path) -> Path:
    """A copy of the package's sources and pyproject.toml, to break on purpose."""
    root = tmp_path / "tree"
    for folder in SOURCE_FOLDERS:
        shutil.copytree(REPO / folder, root / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pt"))
    shutil.copy2(REPO / "pyproject.toml", root / "pyproject.toml")
    return root


@needs_import_linter
@pytest.mark.parametrize("path, line, contract", [
    ("analysis/_bad.py", "from odsplat.sync.align import SyncSettings",
     "analysis imports only the spine and the other stages' __init__"),
    ("hil_sim/_bad.py", "def f():\n    from odsplat.acquisition.session import CaptureSession",  # in a function too
     "hil_sim imports only the spine and the other stages' __init__"),
    # upward: against the layers (spine < acquisition < sync < processing < reconstruction < analysis < hil_sim < app)
    ("odsplat/spine/units.py", "from odsplat.sync import SyncSettings", LAYERS),
    ("odsplat/spine/store.py", "def f():\n    from odsplat.app.config import load_config", LAYERS),
    ("sync/_bad.py", "from odsplat.analysis import AnalyzeSettings", LAYERS),
    ("acquisition/_bad.py", "from odsplat.processing import MagnifySettings", LAYERS),
    ("reconstruction/_bad.py", "from odsplat.hil_sim import SimBench", LAYERS),
    ("analysis/_bad.py", "from odsplat.app.pipeline import run", LAYERS),
    ("odsplat/_stray.py", "X = 1", LAYERS),      # every module in a layer (exhaustive)
    ("odsplat/app/pipeline.py", "def f():\n    from odsplat.processing.magnify import magnify_capture",
     APP),
    ("odsplat/app/viewer/model.py", "from odsplat.reconstruction.raster import rasterize_image",
     APP),
    ("odsplat/app/demo.py", "def f():\n    from odsplat.hil_sim.bench import simulate_capture",
     APP),
])
def test_a_forbidden_import_breaks_its_contract(tree, path, line, contract):
    with open(tree / path, "a") as f:
        f.write("\n" + line + "\n")
    proc = _lint_imports(tree)
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert f"{contract} BROKEN" in proc.stdout, proc.stdout
    assert "1 broken" in proc.stdout, proc.stdout


@needs_import_linter
def test_a_stage_may_import_another_stages_package(tree):
    (tree / "analysis" / "_ok.py").write_text("from odsplat.sync import SyncSettings\n")
    proc = _lint_imports(tree)
    assert proc.returncode == 0, proc.stdout + proc.stderr


MAX_FILE_LINES = 800
MAX_FUNCTION_LINES = 100


def test_no_file_over_800_lines_and_no_function_over_100():
    """Files that do one thing: the package, the bench, the tools and the tests."""
    too_long = []
    for folder in (*SOURCE_FOLDERS, "bench", "tools", "tests"):
        for path in sorted((REPO / folder).rglob("*.py")):
            text = path.read_text()
            rel = path.relative_to(REPO)
            if text.count("\n") > MAX_FILE_LINES:
                too_long.append(f"{rel}: {text.count(chr(10))} lines")
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    if n > MAX_FUNCTION_LINES:
                        too_long.append(f"{rel}:{node.lineno}: {node.name} is {n} lines")
    assert not too_long, "\n".join(too_long)
