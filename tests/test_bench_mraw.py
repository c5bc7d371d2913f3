"""bench/mraw.py runs as a script and prints one JSON line: our .mraw frames equal pyMRAW's on every real sample."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLES = ("beam", "ball_12bit", "showcase", "ball_tiled")


def test_bench_mraw_prints_one_json_line(shared_data):
    out = subprocess.run([sys.executable, str(REPO / "bench" / "mraw.py"), "--tile", "4"], capture_output=True,
                         text=True, timeout=120, cwd=REPO,
                         env={**os.environ, "ODSPLAT_SHARED_DATA": str(shared_data)})
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1, out.stdout
    result = json.loads(lines[0])
    assert result["bench"] == "mraw" and result["skipped"] is None
    # The frames' sizes in MB: beam 4 x 80 x 1024 x 2 bytes, ball 15 x 384 x 384 x 2, showcase 75 x 40 x 640.
    assert (result["beam_mb"], result["ball_12bit_mb"], result["showcase_mb"]) == (0.655, 4.424, 1.92)
    assert result["ball_tiled_mb"] == round(4 * 4.42368, 3)
    for name in SAMPLES:
        assert result[f"{name}_equal"] is True
        assert result[f"{name}_ours_mb_s"] > 0 and result[f"{name}_pymraw_mb_s"] > 0
        assert result[f"{name}_ratio_vs_pymraw"] > 0
