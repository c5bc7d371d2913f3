"""Benchmark of the capture store: write/read throughput of 12-bit frames against np.save/np.load, and compression.

Prints one JSON line on stdout; progress goes to stderr. Throughputs are in MB/s (1 MB = 1e6 bytes)
of uncompressed uint16 frame data on both sides, so the ratios compare the same payload. The temp
files live under Python's `tempfile` directory (set TMPDIR to benchmark another disk).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyMRAW

from odsplat.spine.manifest import CameraInfo, Manifest
from odsplat.spine.shared_data import shared_data_dir
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader

log = logging.getLogger("bench.store")

REPO = Path(__file__).resolve().parents[1]
BIT_DEPTH = 12
REPEATS = 3
READ_CHUNK_FRAMES = 16
FPS = 20_000.0
BALL_CIH = Path("pymraw-samples") / "ball_12bit.cihx"
MB = 1e6


def synthetic_frames(n_frames: int, size: int, *, seed: int = 0) -> np.ndarray:
    """Camera-like 12-bit frames: a smooth speckle texture vibrating by a sub-pixel shift, plus fresh sensor noise.

    Neither zeros nor white noise: both make compression look unrealistically good or bad.
    """
    rng = np.random.default_rng(seed)
    # Speckle of a few pixels: white noise low-passed by a Gaussian of ~2 px in the Fourier domain.
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    speckle_sigma_px = 2.0
    lowpass = np.exp(-2.0 * (np.pi * speckle_sigma_px) ** 2 * (fx**2 + fy**2))
    spectrum = np.fft.rfft2(rng.standard_normal((size, size))) * lowpass
    base = np.fft.irfft2(spectrum, s=(size, size))
    scale = 600.0 / base.std()  # mean 2048, std 600 LSB: uses most of the 12-bit range, rarely clips
    frames = np.empty((n_frames, size, size), dtype=np.uint16)
    for k in range(n_frames):
        # A structure vibrating by up to 1.5 px: the texture moves sub-pixel, so every pixel changes.
        dy, dx = 1.5 * np.sin(2 * np.pi * k / 16.0), 0.7 * np.sin(2 * np.pi * k / 11.0 + 0.3)
        shifted = np.fft.irfft2(spectrum * np.exp(-2j * np.pi * (fy * dy + fx * dx)), s=(size, size))
        img = 2048.0 + scale * shifted + rng.normal(0.0, 4.0, (size, size))
        frames[k] = np.clip(np.rint(img), 0, 2**BIT_DEPTH - 1)
    return frames


def _checksum(block: np.ndarray) -> int:
    # Touches every frame of the block cheaply; the same on both sides, and checks the data came back.
    return int(block[:, 0, :].sum(dtype=np.int64))


def _best_of(fn: Callable[[int], Any], repeats: int = REPEATS) -> tuple[float, Any]:
    """Run fn(rep) `repeats` times; return the shortest wall time and the last result."""
    best = float("inf")
    result = None
    for rep in range(repeats):
        t0 = time.perf_counter()
        result = fn(rep)
        best = min(best, time.perf_counter() - t0)
    return best, result


def _manifest(name: str, shape: tuple[int, int]) -> Manifest:
    return Manifest(
        name=name,
        camera=CameraInfo(model="synthetic", width_px=shape[1], height_px=shape[0], fps=FPS, bit_depth=BIT_DEPTH),
    )


def write_take(root: Path, frames: np.ndarray, name: str) -> Path:
    """Record `frames` as live capture does (one append and flush per frame), finalise; return the take file."""
    cap = Capture.create(root, _manifest(name, frames.shape[1:]))
    writer = cap.new_take(name, frame_shape=frames.shape[1:], dtype=frames.dtype, bit_depth=BIT_DEPTH, fps=FPS)
    for k in range(len(frames)):
        writer.append_frames(frames[k], times_s=[k / FPS], counter=[k])
    record = writer.finalize()
    return cap.root / record.file


def bench_throughput(frames: np.ndarray, tmp: Path) -> dict[str, Any]:
    """Store write/read versus np.save(+fsync)/np.load of the same array, best of REPEATS each."""
    raw_bytes = frames.nbytes
    expected = _checksum(frames)
    take_paths: list[Path] = []

    def store_write(rep: int) -> Path:
        root = tmp / f"store_{rep}"
        path = write_take(root, frames, "bench")
        take_paths.append(path)
        return path

    log.info("store write: %d frames %s, best of %d", len(frames), frames.shape[1:], REPEATS)
    t_store_w, take_path = _best_of(store_write)
    for path in take_paths[:-1]:  # keep one take, for reading
        shutil.rmtree(path.parents[1])

    npy_path = tmp / "frames.npy"

    def npsave_write(rep: int) -> None:
        with open(npy_path, "wb") as fh:
            np.save(fh, frames)
            fh.flush()
            os.fsync(fh.fileno())  # the store's finalize() fsyncs too

    log.info("np.save + fsync, best of %d", REPEATS)
    t_np_w, _ = _best_of(npsave_write)

    # Both files were just written, so both reads come from the page cache (a normal process
    # cannot drop it). That holds for both sides, so the ratio compares decoding, not disks.
    def store_read(rep: int) -> int:
        total = 0
        with TakeReader(take_path) as reader:
            for block in reader.iter_frames(chunk_frames=READ_CHUNK_FRAMES):
                total += _checksum(block)
        return total

    def npload_read(rep: int) -> int:
        arr = np.load(npy_path)  # a full read into memory, not a memmap
        return _checksum(arr)

    log.info("store read (iter_frames, %d frames a block), best of %d", READ_CHUNK_FRAMES, REPEATS)
    t_store_r, store_sum = _best_of(store_read)
    log.info("np.load, best of %d", REPEATS)
    t_np_r, np_sum = _best_of(npload_read)
    if store_sum != expected or np_sum != expected:
        raise RuntimeError(f"read back wrong data: checksums store {store_sum}, np.load {np_sum}, expected {expected}")

    store_bytes = take_path.stat().st_size
    with TakeReader(take_path) as reader:
        frames_stored_bytes = reader.frames.id.get_storage_size()
    write_mb_s = raw_bytes / MB / t_store_w
    read_mb_s = raw_bytes / MB / t_store_r
    npsave_mb_s = raw_bytes / MB / t_np_w
    npload_mb_s = raw_bytes / MB / t_np_r
    return {
        "write_mb_s": round(write_mb_s, 1),
        "read_mb_s": round(read_mb_s, 1),
        "npsave_write_mb_s": round(npsave_mb_s, 1),
        "npload_read_mb_s": round(npload_mb_s, 1),
        "write_ratio_vs_npsave": round(write_mb_s / npsave_mb_s, 3),
        "read_ratio_vs_npload": round(read_mb_s / npload_mb_s, 3),
        "raw_uint16_bytes": raw_bytes,
        "store_file_bytes": store_bytes,
        "npsave_file_bytes": npy_path.stat().st_size,
        # The whole take file, HDF5 metadata and frame times included; dominated by it for tiny takes.
        "synthetic_ratio_vs_uint16": round(raw_bytes / store_bytes, 3),
        # The /frames dataset alone: what the codec does.
        "synthetic_frames_ratio_vs_uint16": round(raw_bytes / frames_stored_bytes, 3),
    }


def bench_ball(tmp: Path) -> dict[str, Any]:
    """Compression of a real 12-bit Photron recording, against uint16 words and the camera's packed 12-bit."""
    cih = shared_data_dir(REPO) / BALL_CIH
    mraw = cih.with_suffix(".mraw")
    if not (cih.is_file() and mraw.is_file()):
        return {
            "ball_12bit_ratio_vs_uint16": None,
            "ball_12bit_ratio_vs_packed12": None,
            "ball_12bit_take_bytes": None,
            "skipped": f"real recording not found at {cih} (set ODSPLAT_SHARED_DATA to the shared data folder)",
        }
    images, info = pyMRAW.load_video(str(cih))
    if images.dtype != np.uint16 or int(images.max()) >= 2**BIT_DEPTH:
        raise RuntimeError(f"{cih}: expected uint16 holding 12-bit values; got {images.dtype}, max {images.max()}")
    log.info("ball_12bit: %d frames %s, %s-bit", len(images), images.shape[1:], info.get("EffectiveBit Depth"))
    path = write_take(tmp / "ball", images, "ball_12bit")
    take_bytes = path.stat().st_size
    return {
        "ball_12bit_ratio_vs_uint16": round(images.nbytes / take_bytes, 3),
        "ball_12bit_ratio_vs_packed12": round(mraw.stat().st_size / take_bytes, 3),
        "ball_12bit_take_bytes": take_bytes,
        "skipped": None,
    }


def peak_rss_mb() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / MB if sys.platform == "darwin" else peak * 1024 / MB  # bytes on macOS, KiB on Linux


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=64, help="number of synthetic frames (default 64)")
    parser.add_argument("--size", type=int, default=1024, help="frame height and width in px (default 1024)")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.size < 8:
        parser.error("--frames must be >= 1 and --size >= 8")
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")

    log.info("generating %d frames of %dx%d", args.frames, args.size, args.size)
    frames = synthetic_frames(args.frames, args.size)
    result: dict[str, Any] = {
        "bench": "store",
        "frames": args.frames,
        "shape": [args.size, args.size],
        "bit_depth": BIT_DEPTH,
        "repeats": REPEATS,
        "cpu_count": os.cpu_count(),
    }
    with tempfile.TemporaryDirectory(prefix="odsplat-bench-") as tmp:
        result.update(bench_throughput(frames, Path(tmp)))
        result.update(bench_ball(Path(tmp)))
    result["peak_rss_mb"] = round(peak_rss_mb(), 1)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
