"""The one table of stages (odsplat/app/stages.py): the configuration, the pipeline's graph and the command line's
stage commands are read from it; its import paths and its TYPE_CHECKING imports name the same things; and the light
commands load no torch, which the table's lazy loading is for."""
from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from odsplat.app import config, pipeline, stages
from odsplat.app.cli import main
from odsplat.app.report import ReportSettings
from odsplat.spine.manifest import ChannelInfo, Manifest
from odsplat.spine.store import Capture

REPO = Path(__file__).resolve().parents[1]


def test_the_configuration_the_graph_and_the_commands_are_the_table():
    names = tuple(s.name for s in stages.TABLE)
    assert names == ("qc", "sync", "magnify", "poses", "reconstruct", "analyze", "report")
    assert config.STAGES == pipeline.STAGES == names and pipeline.GRAPH is stages.TABLE
    assert tuple(config.settings_types()) == names and config.Config.defaults().settings("report") == ReportSettings()
    for st in stages.TABLE:
        assert pipeline.stage(st.name) is st and main.commands[st.name].help == st.doc
        if st.settings_path is not None:
            package, name = st.settings_path.split(":")
            assert config.settings_type(st.name) is getattr(importlib.import_module(package), name)


def test_the_type_checking_imports_name_every_path_of_the_table():
    """The tools see a stage's dependency only through the `if TYPE_CHECKING:` imports: each import path of the
    table must be among them (a stage added to the table alone fails here)."""
    tree = ast.parse((REPO / "odsplat" / "app" / "stages.py").read_text())
    (block,) = [n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING"]
    imported = {f"{node.module}:{alias.name}" for node in block.body if isinstance(node, ast.ImportFrom)
                for alias in node.names}
    paths = {p for st in stages.TABLE for p in (st.settings_path, st.entry_path) if p is not None}
    assert paths <= imported, sorted(paths - imported)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    cap = Capture.create(tmp_path_factory.mktemp("stages") / "cap", Manifest(
        name="t", daq_sample_rate_hz=1000.0, channels=[ChannelInfo("force", "force", "N")]))
    with cap.new_take("a", view=1, frame_shape=(8, 8), dtype=np.uint8, fps=500.0) as w:
        w.append_frames(np.zeros((4, 8, 8), np.uint8))
        w.append_samples({"force": np.zeros(100)})
        w.finalize()
    return cap.root


@pytest.mark.timeout(120)
@pytest.mark.parametrize("args", [["--help"], ["info", "{cap}"], ["verify", "{cap}"], ["qc", "{cap}"],
                                  ["qc", "--help"]])
def test_light_commands_import_no_torch(tiny, args):
    run = subprocess.run([sys.executable, "-X", "importtime", "-m", "odsplat",
                          *(a.replace("{cap}", str(tiny)) for a in args)],
                         capture_output=True, text=True, cwd=REPO, timeout=100)
    assert run.returncode in (0, 1), run.stderr[-2000:]
    imported = [line.rsplit("|", 1)[-1].strip() for line in run.stderr.splitlines() if line.startswith("import time")]
    assert "odsplat.app.cli" in imported and not [m for m in imported if m.split(".")[0] == "torch"]
