"""cv2 must be imported before pycolmap; odsplat does it in one place."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCES = [p for d in ("odsplat", "acquisition", "sync", "processing", "reconstruction", "analysis", "hil_sim")
           for p in (REPO / d).rglob("*.py")]


def test_pycolmap_loads_after_cv2_and_png_writing_works(tmp_path):
    code = (
        "import sys; from odsplat.spine._deps import import_pycolmap; pc = import_pycolmap();"
        "mods = list(sys.modules); assert mods.index('cv2') < mods.index('pycolmap'), 'order';"
        "import cv2, numpy as np;"
        f"assert cv2.imwrite({str(tmp_path / 'x.png')!r}, np.arange(64, dtype=np.uint8).reshape(8, 8));"
        f"assert (cv2.imread({str(tmp_path / 'x.png')!r}, 0) == np.arange(64).reshape(8, 8)).all();"
        "print(pc.__version__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip()


def test_no_module_imports_pycolmap_directly():
    offenders = [str(p.relative_to(REPO)) for p in SOURCES
                 if p.name != "_deps.py" and any(line.strip().startswith(("import pycolmap", "from pycolmap"))
                                                 for line in p.read_text().splitlines())]
    assert offenders == []
