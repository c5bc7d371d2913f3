"""Benchmark of Photron .mraw reading: odsplat's streaming reader (`open_video`) against pyMRAW on the real samples.

Prints one JSON line on stdout; progress goes to stderr. For each sample the whole recording is read into memory
both ways, best of REPEATS, and its frames are checked equal. Timings are given as throughputs in MB/s of the
delivered frames and as ratios (ours / pyMRAW's throughput: above 1 means ours is faster). pyMRAW maps 8- and
16-bit files (a copy to memory is timed, as ours delivers copies) and unpacks a packed 12-bit file whole with its
parallel numba kernel; ours streams `--chunk` frames at a time (the same kernel on each chunk), checks the header
against the file and joins the chunks. The packed 12-bit sample is also timed tiled `--tile` times, so that the
timing is not dominated by fixed costs.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyMRAW

from odsplat.spine.io.video import open_video
from odsplat.spine.shared_data import shared_data_dir

log = logging.getLogger("bench.mraw")

REPO = Path(__file__).resolve().parents[1]
REPEATS = 5
MB = 1e6
SAMPLES = {
    "beam": Path("pymraw-samples") / "beam.cihx",            # 12-bit data in 16-bit words
    "ball_12bit": Path("pymraw-samples") / "ball_12bit.cihx",  # packed 12-bit
    "showcase": Path("pyidi-samples") / "data_showcase.cih",   # 8-bit
}


def _best_of(fn: Callable[[], np.ndarray]) -> tuple[float, np.ndarray]:
    best, result = float("inf"), None
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return best, result


def ours(cih: Path, chunk: int) -> np.ndarray:
    source = open_video(cih)
    return np.concatenate(list(source.iter_chunks(chunk)))


def theirs(cih: Path) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyMRAW warns about anything but 12-bit
        images, _ = pyMRAW.load_video(str(cih))
    return np.array(images)  # 8/16-bit come as a map of the file: copy, as ours delivers


def compare(name: str, cih: Path, chunk: int) -> dict[str, Any]:
    theirs(cih)  # numba compiles (or loads its cache) on the first 12-bit call: not timed
    t_ours, a = _best_of(lambda: ours(cih, chunk))
    t_theirs, b = _best_of(lambda: theirs(cih))
    if not np.array_equal(a, b):
        raise RuntimeError(f"{cih}: our frames differ from pyMRAW's")
    log.info("%s: %d frames %s %s, ours %.4f s, pyMRAW %.4f s", name, len(a), a.shape[1:], a.dtype, t_ours, t_theirs)
    return {f"{name}_mb": round(a.nbytes / MB, 3), f"{name}_ours_mb_s": round(a.nbytes / MB / t_ours, 1),
            f"{name}_pymraw_mb_s": round(a.nbytes / MB / t_theirs, 1),
            f"{name}_ratio_vs_pymraw": round(t_theirs / t_ours, 3), f"{name}_equal": True}


def tiled_ball(cih: Path, tile: int, tmp: Path) -> Path:
    """ball_12bit with its frames repeated `tile` times: a larger packed file of the same content."""
    text = cih.read_bytes()
    n = int(pyMRAW.get_cih(str(cih))["Total Frame"])
    out = tmp / "ball_tiled.cihx"
    out.write_bytes(text.replace(f"<totalFrame>{n}</totalFrame>".encode(), f"<totalFrame>{n * tile}</totalFrame>"
                                 .encode()))
    data = cih.with_suffix(".mraw").read_bytes()
    out.with_suffix(".mraw").write_bytes(data * tile)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunk", type=int, default=64, help="frames per read of ours (default 64, as import)")
    parser.add_argument("--tile", type=int, default=20, help="copies of ball_12bit in the tiled file (default 20)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    result: dict[str, Any] = {"bench": "mraw", "repeats": REPEATS, "chunk_frames": args.chunk,
                              "cpu_count": os.cpu_count(), "skipped": None}
    data = shared_data_dir(REPO)
    missing = [str(data / rel) for rel in SAMPLES.values() if not (data / rel).is_file()]
    if missing:
        result["skipped"] = f"real recordings not found: {missing} (set ODSPLAT_SHARED_DATA)"
        print(json.dumps(result), flush=True)
        return 0
    for name, rel in SAMPLES.items():
        result.update(compare(name, data / rel, args.chunk))
    with tempfile.TemporaryDirectory(prefix="odsplat-bench-") as tmp:
        result.update(compare("ball_tiled", tiled_ball(data / SAMPLES["ball_12bit"], args.tile, Path(tmp)),
                              args.chunk))
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
