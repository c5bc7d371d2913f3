"""Nonsense settings are refused with one line naming the field, exit 2, nothing written: on the command line, with
`odsplat run --set` and in odsplat.toml alike (the settings dataclasses check themselves); settings that depend on the
data (the FRF's band) are checked against it before anything is written; a capture.json of random bytes is one line."""
from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from odsplat.app.cli import main
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.spine.checks import POSITIVE, Range, check_number, maybe
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture

from .conftest import tiny_capture


def _refused(root, *args, field: str) -> str:
    """Run `odsplat ARGS`; it must exit 2 with one line naming `field`, no traceback, and write nothing."""
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert isinstance(r.exception, SystemExit) or r.exception is None, repr(r.exception)
    lines = r.output.strip().splitlines()
    assert r.exit_code == 2 and lines and lines[-1].startswith("odsplat: error: "), r.output
    assert field in lines[-1], lines[-1]
    assert "Traceback" not in r.output
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before, "something was written"
    return lines[-1]


@pytest.fixture()
def small(tmp_path) -> Capture:
    """A capture with one complete take of 10 tiny frames and a force and an acceleration channel."""
    return tiny_capture(tmp_path / "cap")


@pytest.mark.parametrize("args, field", [
    (["magnify", "--option", "n_orientations=many"], "MagnifySettings.options.n_orientations"),
    (["magnify", "--option", "sigma_px=NaN"], "MagnifySettings.options.sigma_px"),
    (["magnify", "--option", "no_such=1"], "MagnifySettings.options.no_such"),
    (["magnify", "--alpha", "inf"], "MagnifySettings.alpha"),
    (["magnify", "--alpha", "1e308"], "MagnifySettings.alpha"),
    (["magnify", "--band", "nan", "30"], "MagnifySettings.band_hz[0]"),
    (["sync", "--trigger-delay-s", "nan"], "SyncSettings.camera_trigger_delay_s"),
    (["sync", "--max-memory-mb", "nan"], "SyncSettings.max_memory_mb"),
    (["sync", "--max-memory-mb", "0"], "SyncSettings.max_memory_mb"),
    (["analyze", "--fmax", "0"], "AnalyzeSettings.fmax_hz"),
    (["analyze", "--fmax", "inf"], "AnalyzeSettings.fmax_hz"),
    (["analyze", "--ods", "nan"], "AnalyzeSettings.ods_freq_hz[0]"),
    (["analyze", "--ods", "-5"], "AnalyzeSettings.ods_freq_hz[0]"),
    (["analyze", "--freq", "0"], "AnalyzeSettings.approx_freq_hz[0]"),
    (["analyze", "--record", "nan"], "AnalyzeSettings.record_s"),
    (["analyze", "--max-order", "0"], "AnalyzeSettings.max_order"),
    (["analyze", "--fmin", "500", "--fmax", "100"], "AnalyzeSettings.fmin_hz"),
    (["qc", "--force-band", "500", "nan"], "QCSettings.force_band_n[1]"),
    (["qc", "--force-band", "500", "100"], "QCSettings.force_band_n"),
    (["reconstruct", "--width", "0"], "ReconstructSettings.width_px"),
    (["reconstruct", "--timesteps", "0"], "ReconstructSettings.n_timesteps"),
    (["render", "--width", "0"], "--width"),
    (["render", "--fps", "nan"], "--fps"),
    (["render", "--camera", "orbit:4:30:-1"], "--camera"),
    (["render", "--camera", "orbit:4:nan"], "--camera"),
    (["render", "--alpha", "inf"], "--alpha"),
])
def test_a_bad_option_is_one_line_naming_the_field(small, args, field):
    _refused(small.root, args[0], small.root, *args[1:], field=field)


@pytest.mark.parametrize("setting, field", [
    ("magnify.alpha=inf", "MagnifySettings.alpha"),
    ("magnify.options=[['n_orientations', 'many']]", "MagnifySettings.options.n_orientations"),
    ("sync.max_memory_mb=nan", "SyncSettings.max_memory_mb"),
    ("analyze.fmax_hz=0", "AnalyzeSettings.fmax_hz"),
    ("analyze.frf.impacts.rebound_fraction=inf", "ImpactSettings.rebound_fraction"),
    ("reconstruct.fit.lr_means=-1", "FitSettings.lr_means"),
    ("reconstruct.modal.lr=nan", "ModalSettings.lr"),
    ("reconstruct.linear.max_nodes=0", "LinearSettings.max_nodes"),
    ("qc.impacts.rebound_fraction=2", "ImpactSettings.rebound_fraction"),
])
def test_run_set_and_the_config_file_get_the_same_checks(small, setting, field):
    _refused(small.root, "run", small.root, "--set", setting, field=field)
    key, _, value = setting.partition("=")
    *tables, name = key.split(".")
    config = small.root.parent / "odsplat.toml"
    config.write_text(f"[{'.'.join(tables)}]\n{name} = {value}\n")
    _refused(small.root, "run", small.root, "--config", config, field=field)


def test_band_settings_are_checked_against_the_data_before_anything_is_written(tmp_path):
    """On a take of the simulated rig (DAQ at 25.6 kHz): fmax above the FRF's last line, ODS lines and picked poles
    outside the FRF's band."""
    out = tmp_path / "cap"
    assert simulate_capture(out, n_views=1, n_frames=24, pretrigger_frames=6, record_s=0.05,
                            settings=SimBenchSettings(seed=1), max_attempts=1).complete
    base = ["analyze", out, "--no-video", "--no-image-poles", "--no-report"]
    line = _refused(out, *base, "--fmax", "20000", field="AnalyzeSettings.fmax_hz")
    assert "12800 Hz" in line  # the DAQ's Nyquist frequency
    _refused(out, *base, "--ods", "1e9", field="AnalyzeSettings.ods_freq_hz")
    _refused(out, *base, "--freq", "1e5", field="AnalyzeSettings.approx_freq_hz")


def test_a_manifest_of_random_bytes_is_one_line_for_every_command(small):
    rng = np.random.default_rng(0)
    (small.root / "capture.json").write_bytes(rng.integers(0, 256, 512, dtype=np.uint8).tobytes())
    for command in ("info", "verify", "recover", "run", "config", "qc", "sync", "magnify", "poses", "reconstruct",
                    "render", "analyze", "report", "geometry"):
        line = _refused(small.root, command, small.root, field="capture.json: not JSON: not UTF-8 text")
        assert str(small.root / "capture.json") in line
    (small.root / "capture.json").write_text("{not json")
    _refused(small.root, "info", small.root, field="capture.json: not valid JSON")


def test_the_number_check_itself():
    for value in (float("nan"), float("inf"), -1.0, 0, True, "3", None):
        with pytest.raises(InputError, match=r"^X\.y: expected a finite number > 0"):
            check_number("X.y", value, POSITIVE)
    check_number("X.y", 1e-300, POSITIVE)
    check_number("X.y", None, maybe(POSITIVE))
    with pytest.raises(InputError, match="an integer >= 1"):
        check_number("X.n", 1.5, Range(at_least=1, integer=True))
