"""The pipeline at scale: each stage of `odsplat run` with the defaults on hil_sim captures of several sizes, its
wall time, core-seconds, peak memory (of every process it starts, summed) and the bytes it writes; and the scaling
exponent of each in frames, pixels and views, fitted over the sizes of a sweep (issue 44, docs/scaling.md).

Each capture is generated once (`odsplat capture --sim --auto`, the arm, 12-bit frames in 16-bit words) under
--out and reused by a later run of the bench. Each stage runs alone, as a user would run it (`odsplat run CAPTURE
--from STAGE --to STAGE`, in its own process): its wall time, its core-seconds (user + system of the process and
every child it waited for, from wait4), its peak resident memory (the sum over the process tree, sampled every
SAMPLE_S, and the largest single process's from wait4), and the bytes of the files it wrote under the capture's
derived/.
Baseline in the same run: reading every raw frame once (the capture's reader, 16 frames at a time), the I/O
floor under every stage.

    bench/scale.py --views 4 --frames 64 --size 256x256               # one capture
    bench/scale.py --sweep frames=32,64,128 --views 4 --size 256x256  # and the exponent in frames
    bench/scale.py --seed                                             # the seed's 27 x 640 x 1024^2 (22.5 GB raw)
    bench/scale.py --seed --binned 4                                  # and the same capture binned to 256^2

One JSON line per capture, then (with --sweep) one with each stage's exponent, on stdout; progress on stderr.
With --binned F, each capture is also copied with its frames binned F x F (`binned_copy`: the same capture seen by
a camera of F times larger pixels, its noise F times lower) and run, then one line compares the two: the video's
noise floor at each sensor (how many times lower at full resolution) and the modes each run judged, with
`video_figures`' MAC and scale against the accelerometers in each capture's line.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.analysis import read_analysis  # noqa: E402
from odsplat.spine.store import Capture  # noqa: E402

log = logging.getLogger("bench.scale")

STAGES = ("qc", "sync", "magnify", "poses", "reconstruct", "analyze", "report")
SAMPLE_S = 0.1          # how often the process tree's memory is read
SEED = {"views": 27, "frames": 640, "size": "1024x1024"}   # the paper's: a Nova S6, 1 s at 640 fps per view


def tree_rss(proc: psutil.Process) -> int:
    """Resident bytes of a process and all its descendants (0 for those gone meanwhile)."""
    total = 0
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def measure(cmd: list[str], log_path: Path) -> dict:
    """Run cmd, its output appended to log_path: wall seconds, core-seconds, peak summed RSS and the largest single
    process's peak (bytes), exit status."""
    peak = 0
    t0 = time.perf_counter()
    with open(log_path, "a") as out:
        p = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        ps = psutil.Process(p.pid)
        done = threading.Event()

        def sample() -> None:
            nonlocal peak
            while not done.is_set():
                peak = max(peak, tree_rss(ps))
                done.wait(SAMPLE_S)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        _, status, ru = os.wait4(p.pid, 0)
        done.set()
        sampler.join()
        p.returncode = os.waitstatus_to_exitcode(status)
    return {"wall_s": time.perf_counter() - t0, "core_s": ru.ru_utime + ru.ru_stime, "peak_rss_bytes": peak,
            "max_process_rss_bytes": ru.ru_maxrss * 1024, "status": p.returncode}


def tree_bytes(path: Path, since: float | None = None) -> int:
    """Bytes of the regular files under path (links not followed); since (a time.time()): only those written since."""
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                st = os.lstat(os.path.join(root, f))
            except OSError:
                continue
            if not os.path.islink(os.path.join(root, f)) and (since is None or st.st_mtime >= since):
                total += st.st_size
    return total


def odsplat(*args: str) -> list[str]:
    return [sys.executable, "-m", "odsplat", *args]


def capture(out: Path, views: int, frames: int, size: str, logf: Path) -> dict:
    """The capture at out, recorded unless it is there already: its record time (None: reused)."""
    if (out / "capture.json").is_file():
        return {"capture_s": None}
    fig = measure(odsplat("capture", str(out), "--sim", "--auto", "--no-window", "--views", str(views),
                          "--frames", str(frames), "--size", size, "--pretrigger-frames", str(min(10, frames // 4)),
                          "--bit-depth", "12"), logf)
    if fig["status"] not in (0, 1):            # 1: a view whose takes QC refused; the run goes on without it
        raise SystemExit(f"odsplat capture failed with status {fig['status']}: see {logf}")
    return {"capture_s": fig["wall_s"]}


def read_all_frames(cap_dir: Path, chunk_frames: int = 16) -> dict:
    """The baseline: every raw frame read once, chunk by chunk, as the stages read them."""
    cap = Capture.open(cap_dir)
    t0 = time.perf_counter()
    n = 0
    for name in cap.take_names():
        with cap.open_take(name) as take:
            total = take.frames.shape[0]
            for a in range(0, total, chunk_frames):
                n += take.read_frames(a, min(a + chunk_frames, total)).nbytes
    return {"wall_s": time.perf_counter() - t0, "bytes": n}


WRITER_ATTRS = {"kind", "odsplat_schema", "complete", "created_utc", "finalized_utc", "take", "view", "fps", "capture",
                "recovered"}   # what the take writer records itself


def binned_copy(src: Path, dst: Path, factor: int) -> Path:
    """The same capture at 1/factor of its resolution: every take's frames binned factor x factor (the mean, as a
    camera of larger pixels would see them, its noise factor times lower), written as new takes through the take
    writer with the same signals, trigger and QC; the camera's intrinsics scaled with them. hil_sim's truth files
    come along. Reused when there already."""
    if (dst / "capture.json").is_file():
        return dst
    cap = Capture.open(src)
    manifest = dataclasses.replace(cap.manifest, takes=[], capture_id="")
    cam = manifest.camera
    if cam.width_px % factor or cam.height_px % factor:
        raise SystemExit(f"--binned {factor}: the frames ({cam.width_px}x{cam.height_px}) do not divide by it")
    k = cam.intrinsics
    intr = None if k is None else dataclasses.replace(k, fx_px=k.fx_px / factor, fy_px=k.fy_px / factor,
                                                      cx_px=(k.cx_px + 0.5) / factor - 0.5,
                                                      cy_px=(k.cy_px + 0.5) / factor - 0.5)
    manifest.camera = dataclasses.replace(cam, width_px=cam.width_px // factor, height_px=cam.height_px // factor,
                                          intrinsics=intr)
    out = Capture.create(dst, manifest)
    for rec in cap.manifest.takes:
        with cap.open_take(rec.name) as r:
            h, w = r.frame_shape[:2]
            attrs = {key: v for key, v in r.attrs.items() if key not in WRITER_ATTRS}
            with out.new_take(rec.name, view=r.view, frame_shape=(h // factor, w // factor, *r.frame_shape[2:]),
                              dtype=r.frames.dtype, bit_depth=r.bit_depth, fps=r.fps, attrs=attrs,
                              daq_t0_s=r.daq_t0_s) as wr:
                times, counter = r.frame_times_s, r.frame_counter
                for a, block in zip(range(0, r.n_frames, 64), r.iter_frames(64)):
                    x = np.asarray(block, np.float64)
                    x = x.reshape(len(x), h // factor, factor, w // factor, factor, *x.shape[3:]).mean(axis=(2, 4))
                    wr.append_frames(np.rint(x).astype(block.dtype), times[a:a + len(x)], counter[a:a + len(x)])
                if r.channel_names:
                    wr.append_samples({name: r.channel(name) for name in r.channel_names})
                for node in r.can_nodes:
                    wr.append_can_samples(node, r.can_times_s(node),
                                          {ch: r.can_channel(ch)[1] for ch in r.can_node_channels(node)})
                wr.set_trigger(r.trigger)
                wr.set_qc(r.qc)
                wr.finalize()
        truth = src / "takes" / f"{rec.name}.truth.npz"
        if truth.is_file():
            shutil.copyfile(truth, dst / "takes" / truth.name)
    for photo in sorted((src / "static").glob("*.png")):   # static photos, binned alike
        img = cv2.imread(str(photo), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(dst / "static" / photo.name),
                    cv2.resize(img, (img.shape[1] // factor, img.shape[0] // factor), interpolation=cv2.INTER_AREA))
    if (src / "hammer_fires.jsonl").is_file():
        shutil.copyfile(src / "hammer_fires.jsonl", dst / "hammer_fires.jsonl")
    return dst


def run_capture(root: Path, views: int, frames: int, size: str, binned: int | None = None) -> dict:
    """Record (or reuse) the capture and run every stage on it; with `binned`, on its binned copy instead."""
    name = f"v{views}_f{frames}_{size}"
    out, logf = root / name, root / f"{name}.log"
    root.mkdir(parents=True, exist_ok=True)
    fig: dict = {"capture": name, "views": views, "frames": frames, "size": size, **capture(out, views, frames, size,
                                                                                            logf)}
    if binned:
        w, h = (int(v) // binned for v in size.split("x"))
        name, fig["size"], fig["binned_from"] = f"{name}_bin{binned}", f"{w}x{h}", size
        out, logf = binned_copy(out, root / name, binned), root / f"{name}.log"
        fig["capture"] = name
    raw = tree_bytes(out / "takes")
    fig["raw_bytes"] = raw
    fig["baseline_read_raw"] = read_all_frames(out)
    derived = out / "derived"
    stages: dict = {}
    for stage in STAGES:
        start = time.time()
        m = measure(odsplat("run", str(out), "--from", stage, "--to", stage), logf)
        if m["status"] != 0:
            raise SystemExit(f"odsplat run --from {stage} failed with status {m['status']}: see {logf}")
        m["written_bytes"] = tree_bytes(derived, since=start - 1.0)   # the files it wrote (mtime's resolution)
        stages[stage] = m
        log.info("%s %s: %.1f s wall, %.1f core-s, peak %.2f GB, wrote %.1f MB", name, stage, m["wall_s"],
                 m["core_s"], m["peak_rss_bytes"] / 1e9, m["written_bytes"] / 1e6)
    fig["stages"] = stages
    fig["video"] = video_figures(Capture.open(out))
    fig["total"] = {"wall_s": sum(m["wall_s"] for m in stages.values()),
                    "core_s": sum(m["core_s"] for m in stages.values()),
                    "peak_rss_bytes": max(m["peak_rss_bytes"] for m in stages.values()),
                    "derived_bytes": tree_bytes(derived), "derived_over_raw": tree_bytes(derived) / max(raw, 1)}
    return fig


def video_figures(cap: Capture) -> dict:
    """What the analysis found: the video's noise floor at the sensors and over the structure, and each mode's
    frequency, whether it was judged (above the floor, separated) and its MAC and scale against the
    accelerometers."""
    doc = read_analysis(cap)
    floor = doc.video.noise_floor if doc.video else None
    if floor is None:
        return {"sensor_sigma_um": None, "sigma_um": None, "modes": []}
    pairs = {p.a: p for p in (doc.correlation.pairs if doc.correlation else ())}
    modes = []
    for i, m in enumerate(floor.modes):
        p = pairs.get(i)
        modes.append({"freq_hz": round(m.freq_hz, 3), "judged": not (m.below_floor or m.not_separated),
                      "mac": p and p.mac, "scale": p and p.scale_factor_abs, "full_field_floor_mac": m.full_field_mac})
    return {"sensor_sigma_um": list(floor.sensor_sigma_um), "sigma_um": floor.sigma_um, "modes": modes}


def compare(full: dict, binned: dict) -> dict:
    """The binned run against the full-resolution one: the noise floor at each sensor (how many times lower at full
    resolution) and the modes each judged."""
    a, b = full["video"], binned["video"]
    ratio = [y / x for x, y in zip(a["sensor_sigma_um"] or [], b["sensor_sigma_um"] or []) if x]
    return {"compare": f"{full['capture']} against {binned['capture']}",
            "sensor_floor_ratio": [round(r, 2) for r in ratio],
            "sensor_floor_ratio_median": float(np.median(ratio)) if ratio else None,
            "judged_full": [m["freq_hz"] for m in a["modes"] if m["judged"]],
            "judged_binned": [m["freq_hz"] for m in b["modes"] if m["judged"]]}


def exponents(rows: list[dict], axis: str) -> dict:
    """Per stage (and the total), the slope of log(wall seconds), log(core-seconds) and log(peak RSS) against
    log(the swept quantity): 1 is linear."""
    x = np.log([_quantity(r, axis) for r in rows])
    out = {}
    for stage in (*STAGES, "total"):
        per = [r["stages"][stage] if stage != "total" else r["total"] for r in rows]
        out[stage] = {k: float(np.polyfit(x, np.log([max(p[k], 1e-9) for p in per]), 1)[0])
                      for k in ("wall_s", "core_s", "peak_rss_bytes")}
    return {"sweep": axis, "values": [_quantity(r, axis) for r in rows], "exponent": out}


def _quantity(row: dict, axis: str) -> float:
    if axis == "pixels":
        w, h = (int(v) for v in row["size"].split("x"))
        return float(w * h)
    return float(row[axis])


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench-out/scale"))
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--size", default="256x256")
    ap.add_argument("--sweep", help="AXIS=V1,V2,V3 with AXIS frames, views or size (sizes as WxH)")
    ap.add_argument("--seed", action="store_true", help=f"the seed's capture: {SEED}")
    ap.add_argument("--binned", type=int, help="also run the capture binned FxF (the same capture at lower resolution)"
                                                 " and compare the noise floors and modes")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s", stream=sys.stderr)
    base = dict(SEED) if a.seed else {"views": a.views, "frames": a.frames, "size": a.size}
    configs = [base]
    axis = None
    if a.sweep:
        axis, _, values = a.sweep.partition("=")
        if axis not in ("frames", "views", "size") or not values:
            ap.error("--sweep: AXIS=V1,V2,... with AXIS frames, views or size")
        configs = [{**base, axis: v if axis == "size" else int(v)} for v in values.split(",")]
    rows = []
    for c in configs:
        row = run_capture(a.out, c["views"], c["frames"], c["size"])
        print(json.dumps(row), flush=True)
        rows.append(row)
        if a.binned:
            low = run_capture(a.out, c["views"], c["frames"], c["size"], binned=a.binned)
            print(json.dumps(low), flush=True)
            print(json.dumps(compare(row, low)), flush=True)
    if axis and len(rows) >= 2:
        fit = exponents(rows, "pixels" if axis == "size" else axis)
        print(json.dumps(fit), flush=True)
        rows.append(fit)
    return rows


if __name__ == "__main__":
    main()
