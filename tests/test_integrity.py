"""Raw takes carry per-chunk checksums: flipped bits in a take the simulated rig wrote are named by `odsplat verify`
and refused by every read with one line; a missing or cut-short take is flagged by info, verify and recover; an older
take without checksums stays readable and verify says it has none."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from odsplat.app.cli import main
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader

from .test_store_can import NODE, _manifest

DAMAGED_FRAMES = (3, 4, 17)


def _odsplat(*args) -> tuple[int, str]:
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert not (r.exception and not isinstance(r.exception, SystemExit)), repr(r.exception)
    return r.exit_code, r.output


@pytest.fixture()
def one_take(tmp_path) -> Capture:
    """One view, one accepted take of 24 frames (400x300) and 1280 DAQ samples from the simulated rig (~1 s)."""
    out = tmp_path / "cap"
    report = simulate_capture(out, n_views=1, n_frames=24, pretrigger_frames=6, record_s=0.05,
                              settings=SimBenchSettings(seed=1), max_attempts=1)
    assert report.complete
    return Capture.open(out)


def _flip_bits(path, dataset: str, chunks, bits_per_chunk: int = 8, seed: int = 0) -> None:
    """Flip bits inside the stored bytes of the given chunks of one dataset (found through HDF5's chunk index)."""
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        spans = [(info.byte_offset, info.size) for info in map(ds.id.get_chunk_info, chunks)]
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(seed)
    for offset, size in spans:
        for pos in rng.choice(size, bits_per_chunk, replace=False):
            data[offset + int(pos)] ^= 1 << int(rng.integers(8))
    path.write_bytes(bytes(data))


def test_flipped_bits_are_named_by_verify_and_refused_by_every_read(one_take):
    cap = one_take
    (record,) = cap.manifest.takes
    path = cap.root / record.file
    code, text = _odsplat("verify", cap.root)
    assert code == 0 and f"{record.name}: ok (24 frames, 1280 samples" in text, text

    _flip_bits(path, "frames", DAMAGED_FRAMES)          # 24 flipped bits in three frames' chunks
    _flip_bits(path, "daq/force", [0], bits_per_chunk=4)
    code, text = _odsplat("verify", cap.root)
    assert code == 1, text
    line = next(ln for ln in text.splitlines() if ln.startswith(record.name))
    assert "DAMAGED" in line and "/frames: frames 3-4, 17 of 24 damaged" in line, line
    assert "/daq/force: samples 0-1279 of 1280 damaged" in line, line
    assert "/daq/acc_tip_z" not in line                 # the other channels are whole

    with TakeReader(path) as r:
        assert r.read_frames(5, 17).shape == (12, 300, 400)   # undamaged frames read as before
        # Each read names the damaged frames within what it asked for.
        for read, named in ((lambda: r.read_frames(0, 24), "frames 3-4, 17 of 24"),
                            (lambda: list(r.iter_frames(8)), "frames 3-4 of 24"),
                            (lambda: r.frames[:, 10:20], "frames 3-4, 17 of 24"),
                            (lambda: r.read_frames(17, 18), "frames 17 of 24")):
            with pytest.raises(InputError) as exc:
                read()
            message = str(exc.value)
            assert "\n" not in message and message.startswith(f"{path}: /frames: {named} damaged"), message
        with pytest.raises(InputError, match=r"/daq/force: samples 0-1279 of 1280 damaged"):
            r.channel("force")
        assert len(r.channel("acc_tip_z")) == 1280

    # A stage that reads the take stops with that one line and writes nothing.
    code, text = _odsplat("qc", cap.root)
    assert code == 2 and text.count("\n") == 1 and "/daq/force: samples 0-1279" in text, text
    assert not cap.paths.qc_json.exists()


def test_a_missing_or_cut_short_take_is_flagged_by_info_verify_and_recover(one_take, tmp_path):
    cap = one_take
    (record,) = cap.manifest.takes
    path = cap.root / record.file
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    code, text = _odsplat("info", cap.root)
    assert code == 0 and f"WARNING take {record.name}: truncated" in text, text
    code, text = _odsplat("verify", cap.root)
    assert code == 1 and f"{record.name}: TRUNCATED: {path}: cut short, holds {len(data) // 2} of its" in text, text
    code, text = _odsplat("recover", cap.root)
    assert code == 1 and f"{record.name}: NOT recoverable here: truncated" in text and "nothing to recover" not in text

    path.unlink()
    code, text = _odsplat("info", "--json", cap.root)
    assert code == 0 and json.loads(text)["takes"][0]["problem"].startswith("missing: ")
    code, text = _odsplat("verify", cap.root)
    assert code == 1 and f"{record.name}: MISSING" in text
    code, text = _odsplat("recover", cap.root)
    assert code == 1 and f"{record.name}: NOT recoverable here: missing" in text


@pytest.mark.parametrize("where", ["root group", "frames"])
def test_a_flipped_byte_in_an_object_header_is_unreadable_in_one_line(one_take, where):
    """h5py reports a garbled object header as a KeyError ("incorrect metadata checksum", or "bad object header
    version number" at its first bytes) on opening the object: any byte of the root group's header (bytes 48 to 570
    of this take, after the superblock) or of `frames`' header, the first dataset a take is opened by. verify, info
    and recover report the take unreadable, one line each, no traceback."""
    cap = one_take
    (record,) = cap.manifest.takes
    path = cap.root / record.file
    with h5py.File(path, "r") as f:
        header = 48 if where == "root group" else h5py.h5o.get_info(f["frames"].id).addr
    data = bytearray(path.read_bytes())
    data[header + 60] ^= 0xFF
    path.write_bytes(bytes(data))
    with h5py.File(path, "r") as f, pytest.raises(KeyError, match="metadata checksum"):
        f["frames"]
    code, text = _odsplat("verify", cap.root)
    line = next(ln for ln in text.splitlines() if ln.startswith(record.name))
    assert code == 1 and line.startswith(f"{record.name}: UNREADABLE: {path}: its HDF5 metadata") and \
        "metadata checksum" in line, text
    code, text = _odsplat("info", cap.root)
    assert code == 0 and f"WARNING take {record.name}: unreadable" in text, text
    code, text = _odsplat("recover", cap.root)
    assert code == 1 and f"{record.name}: NOT recoverable here: unreadable" in text, text


def _without_checksums(path) -> None:
    """Rewrite a take as odsplat wrote it before checksums: every dataset the same, without Fletcher-32."""
    old = path.with_name("old.h5")
    with h5py.File(path, "r") as src, h5py.File(old, "w", libver="latest") as dst:
        dst.attrs.update(src.attrs)

        def copy(name, obj):
            if isinstance(obj, h5py.Group):
                dst.require_group(name).attrs.update(obj.attrs)
                return
            kw = dict(compression=obj.compression, compression_opts=obj.compression_opts) if obj.compression else {}
            if "32001" in obj._filters:
                kw = dict(compression=32001, compression_opts=obj._filters["32001"])
            ds = dst.create_dataset(name, data=obj[...], chunks=obj.chunks, maxshape=obj.maxshape, **kw)
            ds.attrs.update(obj.attrs)

        src.visititems(copy)
    old.replace(path)


def test_an_older_take_without_checksums_stays_readable_and_verify_says_so(one_take):
    cap = one_take
    (record,) = cap.manifest.takes
    path = cap.root / record.file
    with TakeReader(path) as r:
        frames, force = r.read_frames(), r.channel("force")
    _without_checksums(path)
    with h5py.File(path) as f:
        assert not f["frames"].fletcher32 and not f["daq/force"].fletcher32
    with TakeReader(path) as r:
        np.testing.assert_array_equal(r.read_frames(), frames)
        np.testing.assert_array_equal(r.channel("force"), force)
    code, text = _odsplat("verify", cap.root)
    assert code == 0 and f"{record.name}: no checksums: written without per-chunk checksums" in text, text


def test_every_raw_dataset_is_checksummed_and_swmr_recovery_keeps_them(tmp_path):
    """A writer closed mid-take leaves an SWMR-written .partial file; both it and the recovered take carry checksums
    on every dataset and read back whole."""
    cap = Capture.create(tmp_path / "cap", _manifest())
    w = cap.new_take("t", frame_shape=(16, 16), dtype=np.uint8)
    for k in range(5):
        w.append_frames(np.full((16, 16), k, np.uint8))
    w.append_samples({"force": np.ones(300), "acc1": np.zeros(300)})
    t = NODE.t0_daq_s + np.arange(40) / 500.0
    w.append_can_samples("node3", t, {f"node3_{ax}": np.ones(40) for ax in "xyz"})
    w.close_unfinished()
    for path, swmr in ((w.partial_path, True), (cap.takes_dir / "t.h5", False)):
        if not swmr:
            (report,) = cap.recover()
            assert report.recovered and report.n_frames == 5
        with h5py.File(path, "r", swmr=swmr) as f:
            names = []
            f.visit(names.append)
            sets = [f[n] for n in names if isinstance(f[n], h5py.Dataset)]
            assert len(sets) == 9 and all(ds.fletcher32 for ds in sets), [ds.name for ds in sets]
    code, text = _odsplat("verify", cap.root)
    assert code == 0 and "t: ok (5 frames, 300 samples" in text, text
