"""Magnifying every view of a synced capture recorded on the simulated rig."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from odsplat.processing.magnify import MagnifiedVideo, MagnifySettings, magnify_capture, parse_options
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, SyncSettings, load_sync, sync_capture
from odsplat.sync.image import DisplacementBasis

from ..conftest import TRIGGER_DELAY_S

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def synced(sim_capture, tmp_path_factory) -> Capture:
    dest = tmp_path_factory.mktemp("magnify") / "cap"
    shutil.copytree(sim_capture.root, dest, ignore=shutil.ignore_patterns("derived"))
    cap = Capture.open(dest)
    sync_capture(cap, SyncSettings(camera_trigger_delay_s=TRIGGER_DELAY_S, check_with_image=False), progress=False)
    return cap


def _gain(cap: Capture, name: str, before: np.ndarray, after: np.ndarray, times_s: np.ndarray) -> float:
    """The output's motion over the input's, per pixel, through the accelerometers: each pixel's change is
    fitted by the DAQ's displacement signals (noise-free, so the input's noise does not bias the ratio), and
    the output's coefficients are regressed on the input's."""
    sync = load_sync(cap)
    t = next(t for t in sync.ok if t.name == name)
    with cap.open_take(name) as r:
        basis = DisplacementBasis.from_take(r, t.hit_daq_time_s, t.exposure_s)
    m = np.column_stack([basis(t.hit_daq_time_s + times_s - 0.5 * t.exposure_s), np.ones(len(times_s))])

    def coeffs(v: np.ndarray) -> np.ndarray:
        return np.linalg.lstsq(m, v.reshape(len(v), -1), rcond=None)[0][:-1]

    c_in, c_out = coeffs(before), coeffs(after)
    return float((c_out * c_in).sum() / (c_in * c_in).sum())


@pytest.mark.parametrize("method, options, gain_range", [
    ("linear", (("cutoff_wavelength_px", 1.0),), (6.4, 9.6)),  # motion this small needs no cut-off: alpha +-20 %
    ("phase", (), (0.8, 9.6)),  # see docs/magnification-phase.md: the rig's fine texture and thin edges
])
def test_every_view_is_magnified_on_the_common_grid(synced, method, options, gain_range):
    res = magnify_capture(synced, MagnifySettings(method=method, alpha=8.0, workers=2, options=options,
                                                  every_view=True), progress=False)
    assert len(res.takes) == 4 and {t.source for t in res.takes} == {"aligned"}
    for t in res.takes:
        with (MagnifiedVideo(synced.paths.root / t.file) as out,
              AlignedTake(synced, synced.paths.aligned(t.name)) as src):
            assert out.n_frames == src.n_frames
            np.testing.assert_allclose(out.times_s, src.times_s)
            before, after = src.read_frames(), out.read_frames()
        # Magnified where the take moves (the box found in it, roi.py); outside, the input frames as stored (a
        # quarter DN). The gain is the motion's inside the box: outside there is only noise, which the linear
        # method would magnify too.
        assert t.roi_px is not None, t.name
        y0, y1, x0, x1 = t.roi_px
        outside = np.ones(before.shape[1:], bool)
        outside[y0:y1, x0:x1] = False
        assert 0.02 < 1 - outside.mean() < 0.6, t.roi_px
        assert np.abs(after[:, outside] - before[:, outside]).max() <= 0.125 + 1e-3
        gain = _gain(synced, t.name, before[:, y0:y1, x0:x1], after[:, y0:y1, x0:x1], src.times_s)
        assert gain_range[0] < gain < gain_range[1], (t.name, gain)


def test_raw_source_and_bad_settings(synced, tmp_path):
    res = magnify_capture(synced, MagnifySettings(method="linear", alpha=4.0, source="raw", takes=("v00_000",)),
                          progress=False)
    assert [t.source for t in res.takes] == ["raw"]
    # views: the takes of those viewpoints only (sync's kept takes: one per view, the redone ones replaced)
    res = magnify_capture(synced, MagnifySettings(method="linear", alpha=4.0, views=(2,), workers=1, video=False),
                          progress=False)
    view_of = {t.name: t.view for t in synced.manifest.takes}
    assert [view_of[t.name] for t in res.takes] == [2]
    # by default, the first view's only: the one to watch (issue 44)
    res = magnify_capture(synced, MagnifySettings(method="linear", alpha=4.0, workers=1, video=False), progress=False)
    assert [view_of[t.name] for t in res.takes] == [min(view_of[n] for n in synced.take_names())]
    # takes named are all magnified, whatever their views
    named = tuple(sorted(synced.take_names())[-2:])
    res = magnify_capture(synced, MagnifySettings(method="linear", alpha=4.0, workers=1, video=False, takes=named),
                          progress=False)
    assert sorted(t.name for t in res.takes) == list(named)
    with pytest.raises(InputError, match=r"magnify.views: no take to magnify from views \[7\]"):
        magnify_capture(synced, MagnifySettings(views=(7,)), progress=False)
    with pytest.raises(InputError, match="views"):
        MagnifySettings(views=(-1,))
    with pytest.raises(InputError, match=r"MagnifySettings\.alpha: expected a finite number > 0 and <= 10000; got 0"):
        MagnifySettings(alpha=0.0)
    with pytest.raises(InputError, match="fps/2 = 1000 Hz; got 50 to 1500 Hz"):
        magnify_capture(synced, MagnifySettings(method="linear", band_hz=(50.0, 1500.0), takes=("v00_000",), workers=1),
                        progress=False)
    bare = tmp_path / "bare"
    shutil.copytree(synced.root, bare, ignore=shutil.ignore_patterns("derived"))
    with pytest.raises(InputError, match="run `odsplat sync` first"):
        magnify_capture(Capture.open(bare), MagnifySettings(source="aligned"), progress=False)


def test_method_options_from_the_command_line():
    assert parse_options(["warp=True", "n_orientations=8", "sigma_px=1.5", "filter=butter", "levels=[1, 2]"]) == (
        ("warp", True), ("n_orientations", 8), ("sigma_px", 1.5), ("filter", "butter"), ("levels", [1, 2]))
    for bad in ("warp", "=1", "two words=1"):
        with pytest.raises(InputError, match="expected KEY=VALUE"):
            parse_options([bad])


def test_cli_magnify(synced):
    run = subprocess.run([sys.executable, "-m", "odsplat", "magnify", str(synced.root), "--method", "linear",
                          "--alpha", "5", "--band", "15", "400", "--take", "v03_000", "--workers", "1"],
                         capture_output=True, text=True, cwd=REPO, timeout=180)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "1 view(s) magnified by 5 with linear, band 15-400 Hz (butter)" in run.stdout
    bad = subprocess.run([sys.executable, "-m", "odsplat", "magnify", str(synced.root), "--alpha", "-1"],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert bad.returncode == 2 and "MagnifySettings.alpha" in bad.stderr
