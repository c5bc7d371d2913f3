"""Derived files that are empty, cut short, of another format, damaged, edited or copied from another capture: each
file's owner refuses it with one line naming it; the command line exits 2 with that line (no traceback, no
"Aborted!", no hang, and never exit 0 with a changed result); the skip rule sees an edit that keeps a file's size
and modification time. One small capture through `odsplat run` (about a minute) gives every derived file."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from odsplat.analysis import read_analysis, read_results_h5
from odsplat.app.config import load_config
from odsplat.app.pipeline import is_current
from odsplat.processing import MagnifiedVideo, MagnifyResult
from odsplat.reconstruction import DynamicScene, MotionRecord, PoseResult, ReconstructResult, load_ply
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

from .conftest import piped_copy

OTHER_ID = "0123456789abcdef0123456789abcdef"   # another capture's id


@pytest.fixture(scope="module")
def piped(piped_original, tmp_path_factory) -> Capture:
    """Eight views through `odsplat run` (the session's piped capture, copied): every derived file."""
    cap = Capture.open(piped_copy(piped_original, tmp_path_factory.mktemp("corruption") / "cap"))
    assert cap.id != OTHER_ID
    return cap


# ------------------------------------------------------------------ the derived files and their owners' readers

def _first_take(cap: Capture) -> str:
    return load_sync(cap).ok[0].name


@dataclass(frozen=True)
class Kind:
    """A derived file: where it lies under derived/, the files its reader needs beside it, and the read."""

    rel: Callable[[Capture], str]
    read: Callable[[Capture, Path, Capture], Any]   # (the capture as the reader sees it, the file, the original)
    needs: tuple[str, ...] = ()


def _read_frames(reader, generation: str, cap: Capture, path: Path) -> None:
    with (AlignedTake(cap, path, generation) if reader is AlignedTake else reader(path, generation, cap.id)) as f:
        f.read_frames()


KINDS = {
    "trajectories.npz": Kind(lambda c: "reconstruction/trajectories.npz", lambda cap, p, src: DynamicScene.load(cap)),
    "measured_motion.npz": Kind(lambda c: "reconstruction/measured_motion.npz",
                                lambda cap, p, src: MotionRecord.read(p, cap.id)),
    "points.npz": Kind(lambda c: "points.npz", lambda cap, p, src: PoseResult.read(cap), needs=("poses.json",)),
    "poses.json": Kind(lambda c: "poses.json", lambda cap, p, src: PoseResult.read(cap), needs=("points.npz",)),
    "gaussians_t0.ply": Kind(lambda c: "reconstruction/gaussians_t0.ply",
                             lambda cap, p, src: load_ply(p, capture_id=cap.id)),
    "results.h5": Kind(lambda c: "analysis/results.h5", lambda cap, p, src: read_results_h5(p, cap.id)),
    "analysis.json": Kind(lambda c: "analysis/analysis.json", lambda cap, p, src: read_analysis(cap)),
    "reconstruction.json": Kind(lambda c: "reconstruction/reconstruction.json",
                                lambda cap, p, src: ReconstructResult.read(cap)),
    "sync/TAKE.h5": Kind(lambda c: f"sync/{_first_take(c)}.h5",
                         lambda cap, p, src: _read_frames(AlignedTake, load_sync(src).generation, cap, p)),
    "magnified/TAKE.h5": Kind(lambda c: f"magnified/phase/{_first_take(c)}.h5",
                              lambda cap, p, src: _read_frames(MagnifiedVideo, MagnifyResult.read(src, "phase")
                                                               .generation, cap, p)),
}


# ------------------------------------------------------------------ corruptions: (valid file, file to write, capture)

def _bytes(make: Callable[[bytes, Capture], bytes]):
    def corrupt(src: Path, dst: Path, cap: Capture) -> None:
        dst.write_bytes(make(src.read_bytes(), cap))
    return corrupt


def _flip_middle(data: bytes, _) -> bytes:
    b = bytearray(data)
    mid = len(b) // 2
    b[mid:mid + 64] = bytes(x ^ 0xFF for x in b[mid:mid + 64])
    return bytes(b)


def _another_format(data: bytes, cap: Capture) -> bytes:
    """An .h5 where an .npz belongs, an .npz where anything else does."""
    is_npz = data[:2] == b"PK"
    return (cap.paths.analysis_dir / "results.h5" if is_npz else cap.paths.trajectories_npz).read_bytes()


# Per kind of file: (key to remove, (key, wrong shape), (key, wrong type)).
NPZ_EDITS = {"trajectories.npz": ("times_s", ("means_rest_m", lambda a: a[:, :2]), "times_s"),
             "measured_motion.npz": ("displacement_m", ("displacement_m", lambda a: a[:, :-1]), "opacity_logits"),
             "points.npz": ("points_m", ("points_m", lambda a: a[:, :2]), "points_m")}
H5_EDITS = {"results.h5": ("geometry/node_ids", ("geometry/coords_m", lambda a: a[:, :2]), "geometry/coords_m"),
            "sync/TAKE.h5": ("times_s", ("times_s", lambda a: a[:-1]), "source_frame"),
            "magnified/TAKE.h5": ("times_s", ("times_s", lambda a: a[:-1]), "frames")}


def _as_text(a: np.ndarray) -> np.ndarray:
    return np.full(a.shape, "x")


def _npz_edit(kind: str, edit: str):
    def corrupt(src: Path, dst: Path, cap: Capture) -> None:
        with np.load(src) as z:
            arrays = {k: z[k] for k in z.files}
        remove, (shaped, reshape), typed = NPZ_EDITS[kind]
        if edit == "foreign":
            arrays["capture_id"] = np.asarray(OTHER_ID)
        elif edit == "key removed":
            del arrays[remove]
        elif edit == "wrong shape":
            arrays[shaped] = reshape(arrays[shaped])
        else:
            arrays[typed] = _as_text(arrays[typed])
        with open(dst, "wb") as fh:
            np.savez(fh, **arrays)
    return corrupt


def _h5_edit(kind: str, edit: str):
    def corrupt(src: Path, dst: Path, cap: Capture) -> None:
        shutil.copyfile(src, dst)
        remove, (shaped, reshape), typed = H5_EDITS[kind]
        with h5py.File(dst, "a") as f:
            if edit == "foreign":
                f.attrs["capture_id"] = OTHER_ID
            elif edit == "key removed":
                del f[remove]
            else:
                key = shaped if edit == "wrong shape" else typed
                data = f[key][()]
                del f[key]
                if edit == "wrong shape":
                    f.create_dataset(key, data=reshape(data))
                elif key == "frames":
                    f.create_dataset(key, data=data.astype(np.float32))
                else:
                    f.create_dataset(key, data=_as_text(data).astype(object), dtype=h5py.string_dtype())
    return corrupt


# Per index file: (key to remove, an edit to the wrong shape, an edit to the wrong type).
JSON_EDITS = {
    "poses.json": ("views", lambda d: d["views"][0].update(K=[[1.0, 0.0], [0.0, 1.0]]),
                   lambda d: d["views"][0].update(K="a camera")),
    "analysis.json": ("modes", lambda d: d.update(modes={"1": d["modes"]}),
                      lambda d: d["modes"][0].update(freq_hz="a frequency")),
    "reconstruction.json": ("result", lambda d: d.update(result=list(d["result"].values())),
                            lambda d: d["result"].update(n_views="twelve")),
}


def _json_edit(kind: str, edit: str):
    def corrupt(src: Path, dst: Path, cap: Capture) -> None:
        doc = json.loads(src.read_text())
        remove, reshape, retype = JSON_EDITS[kind]
        if edit == "foreign":
            doc["capture_id"] = OTHER_ID
        elif edit == "key removed":
            del doc[remove]
        else:
            (reshape if edit == "wrong shape" else retype)(doc)
        dst.write_text(json.dumps(doc))
    return corrupt


def _ply_edit(kind: str, edit: str):
    def corrupt(src: Path, dst: Path, cap: Capture) -> None:
        data = src.read_bytes()
        if edit == "foreign":
            assert cap.id.encode() in data
            dst.write_bytes(data.replace(cap.id.encode(), OTHER_ID.encode()))
            return
        if edit == "wrong shape":         # the header claims one vertex more than the body holds
            head, body = data.split(b"end_header\n", 1)
            n = int(head.split(b"element vertex ")[1].split(b"\n")[0])
            dst.write_bytes(head.replace(f"element vertex {n}\n".encode(), f"element vertex {n + 1}\n".encode())
                            + b"end_header\n" + body)
            return
        ply = PlyData.read(str(src))
        v = ply["vertex"].data
        if edit == "key removed":
            names = [n for n in v.dtype.names if n != "opacity"]
            out = np.empty(len(v), dtype=[(n, v.dtype[n]) for n in names])
        else:                              # positions as integers
            out = np.empty(len(v), dtype=[(n, "<i4" if n == "x" else v.dtype[n]) for n in v.dtype.names])
            names = v.dtype.names
        for n in names:
            out[n] = v[n]
        PlyData([PlyElement.describe(out, "vertex")], byte_order="<", comments=ply.comments).write(str(dst))
    return corrupt


SEMANTIC = ("foreign", "key removed", "wrong shape", "wrong type")


def _semantic(kind: str, edit: str):
    if kind.endswith(".npz"):
        return _npz_edit(kind, edit)
    if kind.endswith(".h5"):
        return _h5_edit(kind, edit)
    if kind.endswith(".json"):
        return _json_edit(kind, edit)
    return _ply_edit(kind, edit)


BYTES = {
    "empty": _bytes(lambda data, cap: b""),
    "cut to half": _bytes(lambda data, cap: data[:len(data) // 2]),
    "cut to 100 bytes": _bytes(lambda data, cap: data[:100]),
    "random bytes": _bytes(lambda data, cap: np.random.default_rng(0).bytes(len(data))),
    "a PNG renamed": _bytes(lambda data, cap: cap.paths.sync_png.read_bytes()),
    "another format renamed": _bytes(_another_format),
    "bytes flipped in the middle": _bytes(_flip_middle),
}
CASES = [(kind, what) for kind in KINDS for what in (*BYTES, *SEMANTIC)]


# Files whose middle is free space (a small HDF5 file's allocation): the flip goes to the middle of this dataset's
# stored bytes instead, where a change is a change of content.
FLIP_IN = {"sync/TAKE.h5": "source_frame"}


def _flip_dataset(name: str):
    def corrupt(src: Path, dst: Path, cap: Capture) -> None:
        import h5py
        with h5py.File(src, "r") as f:
            info = f[name].id.get_chunk_info(0)
        b = bytearray(src.read_bytes())
        mid = info.byte_offset + info.size // 2 - 32
        b[mid:mid + 64] = bytes(x ^ 0xFF for x in b[mid:mid + 64])
        dst.write_bytes(bytes(b))
    return corrupt


def _corrupt(kind: str, what: str, src: Path, dst: Path, cap: Capture) -> None:
    dst.unlink(missing_ok=True)   # a new file: never an edit through a link to the original
    if what == "bytes flipped in the middle" and kind in FLIP_IN:
        return _flip_dataset(FLIP_IN[kind])(src, dst, cap)
    (BYTES[what] if what in BYTES else _semantic(kind, what))(src, dst, cap)


def _names(text: str, path: Path) -> bool:
    return f"{path.parent.name}/{path.name}" in text


# ------------------------------------------------------------------ every reader refuses every corrupt file

@pytest.mark.parametrize("kind, what", CASES, ids=[f"{k}-{w}".replace(" ", "_") for k, w in CASES])
def test_each_owner_refuses_a_corrupt_file_with_one_line_naming_it(piped, tmp_path, kind, what):
    k = KINDS[kind]
    rel = k.rel(piped)
    derived = tmp_path / "derived"
    for name in (rel, *k.needs):
        (derived / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(piped.paths.root / name, derived / name)
    cap = Capture.open(piped.root, derived=derived)
    path = derived / rel
    k.read(cap, path, piped)                      # the file as written reads
    _corrupt(kind, what, piped.paths.root / rel, path, piped)
    with pytest.raises(InputError) as err:
        k.read(cap, path, piped)
    text = str(err.value)
    assert "\n" not in text and _names(text, path), text
    if what == "foreign":
        assert "belongs to another capture" in text and OTHER_ID in text, text


def test_the_corpus_covers_every_derived_data_file():
    assert len(CASES) >= 60
    assert {"trajectories.npz", "measured_motion.npz", "points.npz", "gaussians_t0.ply", "results.h5",
            "sync/TAKE.h5", "magnified/TAKE.h5", "poses.json"} <= set(KINDS)


# ------------------------------------------------------------------ through the command line

def _copy(cap: Capture, dest: Path, frames: tuple[str, ...] = (), *, all_frames: bool = False) -> Capture:
    """The capture for a command that reads its takes and the small derived files: the raw takes hard-linked (a
    raw take is never written; a stage replaces its files, never writes into them), the derived files copied, less
    the SfM workspace and the frame files (but `frames`; with `all_frames` every one, hard-linked)."""
    src = cap.root

    def ignore(folder: str, names: list[str]) -> list[str]:
        rel = Path(folder).relative_to(src).as_posix()
        skip = ({"poses"} if all_frames else {"sync", "magnified", "poses"}) if rel == "derived" else set()
        return [n for n in names if n in skip]

    def copy(a: str, b: str) -> None:
        parts = Path(a).relative_to(src).parts
        linked = parts[0] == "takes" or (parts[0] == "derived" and parts[1] in ("sync", "magnified")
                                          and a.endswith(".h5"))
        (os.link if linked else shutil.copy2)(a, b)

    shutil.copytree(src, dest, ignore=ignore, copy_function=copy)
    for rel in frames:
        (dest / "derived" / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src / "derived" / rel, dest / "derived" / rel)
    return Capture.open(dest)


def _odsplat(*args) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "odsplat", *map(str, args)], capture_output=True, text=True,
                          timeout=120, env=env)


def _one_error_line(r: subprocess.CompletedProcess, path: Path) -> None:
    out = r.stdout + r.stderr
    assert "Traceback" not in out and "Aborted!" not in out, out
    errors = [line for line in out.splitlines() if line.startswith("odsplat: error:")]
    assert r.returncode == 2 and len(errors) == 1 and _names(errors[0], path), out


CLI_CASES = [("analyze", "trajectories.npz", "empty"),
             ("analyze", "trajectories.npz", "cut to half"),
             ("analyze", "measured_motion.npz", "foreign"),
             ("analyze", "poses.json", "bytes flipped in the middle"),
             ("analyze", "points.npz", "random bytes"),
             ("report", "analysis.json", "cut to half"),
             ("export-video", "sync/TAKE.h5", "bytes flipped in the middle")]


@pytest.mark.parametrize("command, kind, what", CLI_CASES,
                         ids=[f"{c}-{k}-{w}".replace(" ", "_") for c, k, w in CLI_CASES])
def test_the_command_line_stops_with_one_line_and_changes_nothing(piped, tmp_path, command, kind, what):
    rel = KINDS[kind].rel(piped)
    cap = _copy(piped, tmp_path / "cap", frames=(rel, ) if rel.endswith(".h5") else ())
    path = cap.paths.root / rel
    outputs = [p for p in (cap.paths.analysis_json, cap.paths.analysis_dir / "results.h5", cap.paths.report_html)
               if p != path]
    before = {p: p.read_bytes() for p in outputs}
    _corrupt(kind, what, piped.paths.root / rel, path, piped)
    args = [command, cap.root] + (["--take", _first_take(piped), "--source", "sync", "-o", tmp_path / "v.mp4"]
                                  if command == "export-video" else [])
    _one_error_line(_odsplat(*args), path)
    assert {p: p.read_bytes() for p in outputs} == before     # no result changed, none half-written
    assert not (tmp_path / "v.mp4").exists()


# ------------------------------------------------------------------ the skip rule reads content

def _keep_size_and_time(path: Path, edit: Callable[[bytearray], None]) -> None:
    st = path.stat()
    data = bytearray(path.read_bytes())
    edit(data)
    path.unlink()                                  # a new file: never an edit through a link
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)


def test_an_edit_that_keeps_size_and_modification_time_makes_the_stage_stale(piped, tmp_path):
    cap = _copy(piped, tmp_path / "cap")
    config = load_config(cap)
    assert is_current(cap, "reconstruct", config) == (True, "current")
    path = cap.paths.measured_motion_npz
    _keep_size_and_time(path, lambda data: data.__setitem__(len(data) // 2, data[len(data) // 2] ^ 0x01))
    assert is_current(cap, "reconstruct", config) == (False, "its outputs changed on disk")
    # A stamp an older odsplat wrote (outputs by size and time) reads as stale, not as an error.
    stamp = cap.paths.stamp("analyze")
    doc = json.loads(stamp.read_text())
    stamp.write_text(json.dumps({**doc, "schema_version": 1}))
    assert is_current(cap, "analyze", config) == (False, "stamped by an older odsplat")


def test_odsplat_run_redoes_a_stage_whose_output_was_edited_in_place(piped, tmp_path):
    """A hostile edit that keeps the file's size and time (bytes flipped in trajectories.npz) is seen by
    `odsplat run`: the reconstruction runs again and replaces the damaged file, and the analysis after it finds
    the same modes and MAC. Nothing is read from the damaged file."""
    cap = _copy(piped, tmp_path / "cap", all_frames=True)
    path = cap.paths.trajectories_npz
    _keep_size_and_time(path, lambda data: data.__setitem__(slice(len(data) // 2, len(data) // 2 + 64),
                                                            bytes(64)))
    with pytest.raises(InputError, match="CRC"):
        DynamicScene.load(cap)
    r = _odsplat("run", cap.root)
    out = r.stdout + r.stderr
    assert r.returncode == 0 and "Traceback" not in out, out
    assert "[reconstruct] running (its outputs changed on disk)" in out, out
    assert "[sync] current, skipped" in out and "[poses] current, skipped" in out, out
    DynamicScene.load(cap)
    again, first = read_analysis(cap), read_analysis(piped)
    assert [m.freq_hz for m in again.modes] == [m.freq_hz for m in first.modes]
    mac = [p.mac for p in again.correlation.pairs]     # the reconstruction is seeded: the same motion
    assert mac == pytest.approx([p.mac for p in first.correlation.pairs], abs=1e-6)
