"""Hostile settings are refused with one line naming the setting, fast: values past every bound (1e12 iterations,
1e308, nan, a million workers), wrong types, tables nested a hundred thousand deep, unknown keys and huge lists;
through `--set`, odsplat.toml, Config.updated and the command line alike. Every numeric field of every stage's
settings has an upper bound (docs/config.md, "Bounds"), and a new field without one fails here."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import typing
from pathlib import Path
from typing import Any

import pytest
import torch
from click.testing import CliRunner

from odsplat.app.cli import main
from odsplat.app.config import Config, load_config, settings_types
from odsplat.spine.checks import (
    MAX_FREQUENCY_HZ,
    MAX_MAGNIFICATION,
    MAX_VIDEO_FREQUENCY_HZ,
    Range,
    check_number,
    shown,
)
from odsplat.spine.errors import InputError
from odsplat.spine.io.limits import FRAME_RATE_HZ, SAMPLE_RATE_HZ
from odsplat.spine.manifest import ChannelInfo, Manifest
from odsplat.spine.store import Capture

REPO = Path(__file__).resolve().parents[1]
LONGEST_LINE = 1000   # characters: an error quotes a hostile value cut short (and may list the fields there are)

_DEEP = "[" * 3000 + "]" * 3000             # past Python's recursion limit when parsed
_DEEPER_THAN_ALLOWED = "[" * 20 + "]" * 20  # parses, but nests past MAX_TOML_DEPTH

# (--set item, what the one line must name, what it names when the same key and value come from a file: None where
# the value is not TOML, so only --set can carry it, "" where the file says the same)
CORPUS: list[tuple[str, str, str | None]] = [
    # huge integers
    ("analyze.max_order=1000000000000", "AnalyzeSettings.max_order", ""),
    ("analyze.frf.n_fft=1000000000000000", "estimate_frf: settings.n_fft", ""),
    ("reconstruct.width_px=100000000", "ReconstructSettings.width_px", ""),
    ("reconstruct.fit.iters_t0=1000000000000000000", "FitSettings.iters_t0", ""),
    ("reconstruct.fit.iters_per_step=" + "9" * 30, "FitSettings.iters_per_step", ""),
    ("reconstruct.linear.max_nodes=" + "9" * 400, "LinearSettings.max_nodes", ""),
    ("magnify.chunk_frames=" + "1" * 5000, "magnify.chunk_frames", "4300 digits"),
    ("magnify.workers=1000000", "MagnifySettings.workers", ""),
    ("sync.workers=1000000", "SyncSettings.workers", ""),
    ("reconstruct.threads=100000", "ReconstructSettings.threads", ""),
    ("poses.threads=100000", "PoseSettings.threads", ""),
    ("reconstruct.modal.iters=10000000", "ModalSettings.iters", ""),
    ("reconstruct.n_timesteps=10000000", "ReconstructSettings.n_timesteps", ""),
    ("reconstruct.start=100000000000", "ReconstructSettings.start", ""),
    ("poses.max_features=100000000", "PoseSettings.max_features", ""),
    ("reconstruct.fit.seed=18446744073709551616", "FitSettings.seed", ""),
    ("reconstruct.modal.n_components=100000", "ModalSettings.n_components", ""),
    ("reconstruct.linear.k_graph=1000000", "LinearSettings.k_graph", ""),
    ("analyze.k_neighbours=1000000000", "AnalyzeSettings.k_neighbours", ""),
    ("analyze.crosscheck_points=100000000", "AnalyzeSettings.crosscheck_points", ""),
    ("analyze.video_ranks=[1000000]", "AnalyzeSettings.video_ranks[0]", ""),
    ("reconstruct.fit.max_gaussians=10000000000", "FitSettings.max_gaussians", ""),
    # the largest floats, either sign
    ("magnify.alpha=1e308", "MagnifySettings.alpha", ""),
    ("magnify.alpha=-1e308", "MagnifySettings.alpha", ""),
    ("magnify.alpha=1e5", "<= 10000", ""),
    ("analyze.fmax_hz=1e308", "AnalyzeSettings.fmax_hz", ""),
    ("analyze.fmin_hz=-1e308", "AnalyzeSettings.fmin_hz", ""),
    ("sync.max_memory_mb=1e308", "SyncSettings.max_memory_mb", ""),
    ("sync.camera_trigger_delay_s=-1e308", "SyncSettings.camera_trigger_delay_s", ""),
    ("sync.search_frames=1e9", "SyncSettings.search_frames", ""),
    ("qc.force_band_n=[0, 1e308]", "QCSettings.force_band_n[1]", ""),
    ("magnify.band_hz=[1, 1e308]", "MagnifySettings.band_hz[1]", ""),
    ("reconstruct.fit.lr_means=1e308", "FitSettings.lr_means", ""),
    ("reconstruct.linear.smoothing=1e308", "LinearSettings.smoothing", ""),
    ("reconstruct.linear.blur_px=1e308", "LinearSettings.blur_px", ""),
    ("reconstruct.modal.blur_px=1e30", "ModalSettings.blur_px", ""),
    ("analyze.record_s=1e308", "AnalyzeSettings.record_s", ""),
    ("analyze.pretrigger_s=1e308", "AnalyzeSettings.pretrigger_s", ""),
    ("analyze.frf.force_window_s=1e308", "estimate_frf: settings.force_window_s", ""),
    ("magnify.video_fps=1e308", "MagnifySettings.video_fps", ""),
    ("analyze.structure_box_m=[[0, 0, 0], [1e308, 1e308, 1e308]]", "AnalyzeSettings.structure_box_m", ""),
    ("analyze.ods_freq_hz=[1e308]", "AnalyzeSettings.ods_freq_hz[0]", ""),
    ("analyze.outlier_factor=1e300", "AnalyzeSettings.outlier_factor", ""),
    # nan and inf, as TOML and as words
    ("magnify.alpha=nan", "MagnifySettings.alpha", ""),
    ("magnify.alpha=inf", "MagnifySettings.alpha", ""),
    ("analyze.fmax_hz=-inf", "AnalyzeSettings.fmax_hz", ""),
    ("sync.search_frames=nan", "SyncSettings.search_frames", ""),
    ("reconstruct.init_opacity=nan", "ReconstructSettings.init_opacity", ""),
    ("magnify.alpha='inf'", "magnify.alpha: expected a number", ""),
    ("analyze.fmax_hz=NaN", "analyze.fmax_hz: expected a number", None),
    ("reconstruct.fit.lr_means=1e999", "FitSettings.lr_means", ""),
    # negative counts and zero
    ("magnify.chunk_frames=0", "MagnifySettings.chunk_frames", ""),
    ("magnify.workers=-4", "MagnifySettings.workers", ""),
    ("reconstruct.step=0", "ReconstructSettings.step", ""),
    ("reconstruct.fit.densify_every=0", "FitSettings.densify_every", ""),
    ("analyze.max_order=-1", "AnalyzeSettings.max_order", ""),
    ("reconstruct.linear.chunk_frames=-1", "LinearSettings.chunk_frames", ""),
    ("magnify.views=[-1]", "MagnifySettings.views[0]", ""),
    ("poses.min_registered=0", "PoseSettings.min_registered", ""),
    ("poses.seed=-1", "PoseSettings.seed", ""),
    ("analyze.frf.n_fft=0", "estimate_frf: settings.n_fft", ""),
    ("magnify.video_fps=0", "MagnifySettings.video_fps", ""),
    # wrong types
    ("analyze.frf.n_fft=1e15", "analyze.frf.n_fft: expected an integer", ""),
    ("analyze.max_order=true", "analyze.max_order: expected an integer", ""),
    ("magnify.alpha=[1, 2]", "magnify.alpha: expected a number", ""),
    ("magnify.alpha={a=1}", "magnify.alpha: expected a number", ""),
    ("reconstruct.fit=[1, 2]", "expected an object for FitSettings", ""),
    ("reconstruct.fit=3", "expected an object for FitSettings", ""),
    ("sync.plot=1", "sync.plot: expected true or false", ""),
    ("poses.masks_dir=5", "poses.masks_dir: expected a path", ""),
    ("analyze.takes=7", "analyze.takes: expected a string", ""),
    ("magnify.band_hz=20", "magnify.band_hz: expected a list", ""),
    ("magnify.band_hz=[1, 2, 3]", "magnify.band_hz: expected 2 values", ""),
    ("analyze.structure_box_m=[[0, 0], [1, 1]]", "analyze.structure_box_m[0]: expected 3 values", ""),
    ("magnify.options=5", "magnify.options: expected a list", ""),
    ("magnify.options=[['n_orientations', 1000000]]", "MagnifySettings.options.n_orientations", ""),
    ("magnify.options=[['batch_frames', 1e12]]", "MagnifySettings.options.batch_frames", ""),
    ("magnify.options=[['sigma_px', 1e308]]", "MagnifySettings.options.sigma_px", ""),
    ("magnify.options=[['levels', " + "[" * 10 + "]" * 10 + "]]", "MagnifySettings.options.levels", ""),
    # enumerated strings
    ("sync.method=fast", "SyncSettings.method", None),
    ("magnify.method=" + "x" * 5000, "MagnifySettings.method", None),
    ("magnify.mode=sideways", "MagnifySettings.mode", None),
    ("poses.takes=some", "PoseSettings.takes", None),
    ("reconstruct.fit.backend=cuda", "FitSettings.backend", None),
    ("reconstruct.modal.loss=l3", "ModalSettings.loss", None),
    ("reconstruct.source='magnified/../../etc'", "source: expected 'sync' or 'magnified/METHOD'", ""),
    ("magnify.filter=kalman", "MagnifySettings.filter", None),
    ("magnify.source=cloud", "MagnifySettings.source", None),
    # deep nesting
    ("magnify.alpha=" + _DEEP, "--set magnify.alpha: nested too deep", "nested too deep"),
    ("magnify.alpha=" + _DEEPER_THAN_ALLOWED, "--set magnify.alpha: nested too deep", "nested too deep"),
    ("magnify.alpha=" + "{a=" * 3000 + "1" + "}" * 3000, "'magnify.alpha=", "nested too deep"),
    ("reconstruct" + ".fit" * 1000 + ".x=1", "'reconstruct.fit.fit.fit.fit.", "nested too deep"),
    ("reconstruct" + ".fit" * 5 + ".x=1", "unknown field(s) ['fit']", ""),
    # unknown keys
    ("magnify.alhpa=3", "magnify: unknown field(s) ['alhpa']", ""),
    ("render.width=3", "unknown stage(s) ['render']", ""),
    ("reconstruct.fit.no_such=1", "reconstruct.fit: unknown field(s) ['no_such']", ""),
    ("magnify.options=[['no_such', 1]]", "MagnifySettings.options.no_such", ""),
    # huge lists
    ("analyze.ods_freq_hz=[" + ",".join(["100"] * 2000) + "]", "AnalyzeSettings.ods_freq_hz: expected at most", ""),
    ("magnify.views=[" + ",".join(["1"] * 3000) + "]", "MagnifySettings.views: expected at most 1000", ""),
    ("magnify.band_hz=[" + "1," * 4000 + "2]", "magnify.band_hz: expected 2 values; got 4001", ""),
    ("analyze.approx_freq_hz=[" + ",".join(["10"] * 5000) + "]", "at most 10000 characters",
     "AnalyzeSettings.approx_freq_hz: expected at most 1000"),
]


def _id(case: tuple[str, str, str | None]) -> str:
    return case[0] if len(case[0]) < 60 else f"{case[0][:40]}...({len(case[0])} chars)"


def _one_line(exc: BaseException) -> str:
    text = str(exc)
    assert "\n" not in text and len(text) < LONGEST_LINE, text[:2000]
    return text


@pytest.mark.timeout(30)
@pytest.mark.parametrize("item, names, _file", CORPUS, ids=[_id(c) for c in CORPUS])
def test_an_abusive_set_is_one_line_naming_the_setting(item, names, _file):
    with pytest.raises(InputError) as err:
        load_config(sets=(item,))
    assert names in _one_line(err.value)


@pytest.mark.timeout(30)
@pytest.mark.parametrize("item, names, file_names", [c for c in CORPUS if c[2] is not None],
                         ids=[_id(c) for c in CORPUS if c[2] is not None])
def test_the_same_in_odsplat_toml_is_refused_alike(tmp_path, item, names, file_names):
    key, _, value = item.partition("=")
    path = tmp_path / "odsplat.toml"
    path.write_text(f"{key} = {value}\n")
    with pytest.raises(InputError) as err:
        load_config(path=path)
    assert (file_names or names) in _one_line(err.value)


def _nested(depth: int, leaf: Any) -> Any:
    for _ in range(depth):
        leaf = [leaf]
    return leaf


@pytest.mark.timeout(30)
@pytest.mark.parametrize("table, names", [
    ({"magnify": {"alpha": 10 ** 5000}}, "an integer of about 5001 digits"),
    ({"magnify": {"alpha": _nested(100_000, 1.0)}}, "magnify.alpha: expected a number; got [[[[...]]]]"),
    ({"analyze": {"ods_freq_hz": _nested(100_000, 1.0)}}, "analyze.ods_freq_hz[0]: expected a number"),
    ({"magnify": {"band_hz": _nested(100_000, 1.0)}}, "magnify.band_hz: expected 2 values; got 1"),
    ({"magnify": {"method": "x" * 10 ** 6}}, "MagnifySettings.method"),
    ({"magnify": {"takes": 5}}, "magnify.takes: expected a list"),
    ({"sync": {"workers": 2 ** 100}}, "SyncSettings.workers"),
    ({"analyze": {"frf": {"fmax_hz": 10 ** 400}}}, "analyze.frf.fmax_hz: expected a finite number"),
    ({f"k{i}": {} for i in range(100_000)}, "unknown stage(s) ['k0', 'k1', 'k10', "),
    ({"magnify": {f"k{i}": 1 for i in range(100_000)}}, "unknown field(s) ['k0', 'k1', 'k10', "),
    ({"magnify": "fast"}, "[magnify]: expected a table of settings"),
])
def test_config_updated_refuses_python_values_past_what_toml_makes(table, names):
    with pytest.raises(InputError) as err:
        Config.defaults().updated(table, "test")
    assert names in _one_line(err.value)


# ---------------------------------------------------------------------------------------------- odsplat.toml


@pytest.mark.timeout(30)
@pytest.mark.parametrize("text, names", [
    ("[magnify]\nalpha = " + "[" * 100_000 + "]" * 100_000 + "\n", "nested too deep"),
    ("[magnify]\nalpha = " + "{a = " * 100_000 + "1" + "}" * 100_000 + "\n", "nested too deep"),
    ("[magnify" + ".a" * 100_000 + "]\nx = 1\n", "nested too deep: more than 16 levels"),
    ("[magnify]\nalpha = " + "9" * 10_000 + "\n", "4300 digits"),
    ("[magnify]\nalpha = 1\n" + "".join(f"# {'x' * 100}\n" for _ in range(50_000)), "MiB: too large for a TOML file"),
])
def test_a_hostile_configuration_file_is_one_line_naming_it(tmp_path, text, names):
    path = tmp_path / "odsplat.toml"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        load_config(path=path)
    line = _one_line(err.value)
    assert line.startswith(str(path)) and names in line


# ---------------------------------------------------------------------------------------------- every field


def _numeric_fields(cls: type, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any]]:
    """(path of names, type) of every numeric field of a settings dataclass and those nested in it: int, float,
    and tuples of them; bools, strings, paths and free-form options are left out."""
    found = []
    for f in dataclasses.fields(cls):
        tp = typing.get_type_hints(cls)[f.name]
        if typing.get_origin(tp) in (typing.Union, typing.get_origin(int | None)):
            (tp,) = [a for a in typing.get_args(tp) if a is not type(None)]
        if dataclasses.is_dataclass(tp):
            found += _numeric_fields(tp, (*path, f.name))
        elif tp in (int, float) or (typing.get_origin(tp) is tuple and _numbers_in(tp)):
            found.append(((*path, f.name), tp))
    return found


def _numbers_in(tp: Any) -> bool:
    args = [a for a in typing.get_args(tp) if a is not Ellipsis]
    return bool(args) and all(a in (int, float) or (typing.get_origin(a) is tuple and _numbers_in(a)) for a in args)


def _enormous(tp: Any, sign: int) -> Any:
    """A value of type `tp` with an enormous number of `sign` where only a bound can catch it: the high end of a
    (low, high) pair, the far corner of a box, the rest in order (low below high)."""
    args = typing.get_args(tp)
    if tp in (int, float) or (len(args) == 2 and args[1] is Ellipsis):
        return _shaped(tp, sign * 1e30)
    parts = [_shaped(a, 1.0 + i) for i, a in enumerate(args)]
    end = -1 if sign > 0 else 0
    parts[end] = _shaped(args[end], sign * 1e30)
    return parts


def _shaped(tp: Any, x: float) -> Any:
    """`x` as `tp` holds it: an int or a float, or a list of them (one for a tuple of any length)."""
    if tp in (int, float):
        return tp(x)
    return [_shaped(a, x) for a in typing.get_args(tp) if a is not Ellipsis]


FIELDS = [(stage, path, tp) for stage, cls in settings_types().items() for path, tp in _numeric_fields(cls)]


def test_the_walk_finds_the_fields():
    names = {".".join((stage, *path)) for stage, path, _ in FIELDS}
    assert {"magnify.alpha", "magnify.band_hz", "magnify.views", "reconstruct.fit.iters_t0", "reconstruct.width_px",
            "reconstruct.linear.max_nodes", "reconstruct.modal.iters", "analyze.frf.n_fft", "analyze.max_order",
            "analyze.structure_box_m", "qc.force_band_n", "sync.workers", "poses.seed"} <= names
    assert len(FIELDS) > 100


@pytest.mark.timeout(60)
@pytest.mark.parametrize("sign", [1, -1], ids=["1e30", "-1e30"])
def test_every_numeric_setting_has_bounds(sign):
    """Each numeric field of each stage's settings, nested ones too, set in turn to an enormous value (1e30, -1e30)
    must be refused naming that field. A new field needs its Range in its class's __post_init__ to pass."""
    unbounded = []
    for stage, path, tp in FIELDS:
        table: dict[str, Any] = {path[-1]: _enormous(tp, sign)}
        for name in reversed((stage, *path[:-1])):
            table = {name: table}
        try:
            Config.defaults().updated(table, "test")
        except InputError as exc:
            line = _one_line(exc)
            if path[-1] not in line or not any(b in line for b in ("<" if sign > 0 else ">", "within")):
                unbounded.append(f"{'.'.join((stage, *path))}: refused, but not for a bound naming it: {exc}")
        else:
            unbounded.append(f"{'.'.join((stage, *path))} = {shown(_enormous(tp, sign))} accepted")
    assert not unbounded, "\n".join(unbounded)


def test_the_bounds_agree_with_the_recording_limits():
    assert MAX_FREQUENCY_HZ == SAMPLE_RATE_HZ[1] / 2 and MAX_VIDEO_FREQUENCY_HZ == FRAME_RATE_HZ[1] / 2


def test_the_range_check_on_hostile_numbers():
    rule = Range(at_least=1, at_most=2 ** 24, integer=True)
    assert "<= 16777216" in rule.describe()
    for value in (10 ** 400, -(10 ** 400), 2 ** 24 + 1, float("nan"), 1e308, True):
        with pytest.raises(InputError, match=r"^X\.n: expected an integer >= 1 and <= 16777216; got "):
            check_number("X.n", value, rule)
    assert not Range().holds(10 ** 400)   # no float holds it: as good as infinite
    assert shown(10 ** 5000) == "an integer of about 5001 digits"
    assert len(shown("x" * 10 ** 6)) < 80


@pytest.mark.timeout(60)
def test_at_the_magnification_bound_every_method_keeps_its_frames_finite():
    """alpha = MAX_MAGNIFICATION on a pattern moving by a pixel: the frames stay finite, in [0, 1] (at 1e308 they
    were all zeros)."""
    from odsplat.processing.eulerian import LinearMagnifier
    from odsplat.processing.phase import PhaseMagnifier

    base = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    frames = torch.cat([torch.roll(base, shifts=(0, k % 2), dims=(2, 3)) for k in range(6)])
    for magnifier in (PhaseMagnifier(MAX_MAGNIFICATION), PhaseMagnifier(MAX_MAGNIFICATION, warp=True),
                      LinearMagnifier(MAX_MAGNIFICATION)):
        out = torch.cat([magnifier.push(frames), magnifier.flush()])
        assert out.shape == frames.shape and torch.isfinite(out).all() and 0 <= out.min() <= out.max() <= 1
    with pytest.raises(InputError, match=r"^alpha: expected a finite number > 0 and <= 10000; got 1e\+308"):
        PhaseMagnifier(1e308)


def test_the_learned_modes_are_the_settings_modes():
    from odsplat.processing.learned import MODES
    from odsplat.processing.magnify import MODES as SETTINGS_MODES

    assert SETTINGS_MODES == MODES


# ---------------------------------------------------------------------------------------------- the command line


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> Capture:
    """A capture with no takes: enough for every check that comes before a stage reads anything."""
    return Capture.create(tmp_path_factory.mktemp("abuse") / "cap", Manifest(
        name="abuse", daq_sample_rate_hz=1000.0, channels=[ChannelInfo("force", "force", "N")]))


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*"))


CLI_SETS = [
    ("analyze.max_order=1000000000000", "AnalyzeSettings.max_order"),
    ("analyze.frf.n_fft=1000000000000000", "n_fft"),
    ("reconstruct.width_px=100000000", "ReconstructSettings.width_px"),
    ("reconstruct.fit.iters_t0=1000000000000000000", "FitSettings.iters_t0"),
    ("magnify.alpha=1e308", "MagnifySettings.alpha"),
    ("magnify.workers=1000000", "MagnifySettings.workers"),
    ("reconstruct.threads=100000", "ReconstructSettings.threads"),
    ("magnify.alpha=" + _DEEP, "magnify.alpha: nested too deep"),
    ("sync.method=" + "x" * 50_000, "at most 10000 characters"),
    ("magnify.band_hz=[1, 1e308]", "MagnifySettings.band_hz[1]"),
]


IN_A_PROCESS = {CLI_SETS[0][0], CLI_SETS[4][0], CLI_SETS[7][0]}   # the rest through click in this process


@pytest.mark.timeout(30)
@pytest.mark.parametrize("item, names", CLI_SETS, ids=[c[0][:40] for c in CLI_SETS])
def test_the_real_command_line_refuses_an_abusive_set_in_one_line(bare, item, names):
    before = _files(bare.root)
    if item in IN_A_PROCESS:
        run = subprocess.run([sys.executable, "-m", "odsplat", "config", str(bare.root), "--set", item],
                             capture_output=True, text=True, cwd=REPO, timeout=30)
        code, out, err = run.returncode, run.stdout, run.stderr
    else:
        result = CliRunner().invoke(main, ["config", str(bare.root), "--set", item])
        code, out, err = result.exit_code, "", result.output
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("odsplat: error: "), err[-3000:]
    assert names in lines[0] and len(lines[0]) < LONGEST_LINE and "Traceback" not in err
    assert out == "" and _files(bare.root) == before


@pytest.mark.timeout(30)
def test_the_real_command_line_names_a_configuration_file_nested_too_deep(bare, tmp_path):
    path = tmp_path / "odsplat.toml"
    path.write_text("[reconstruct.fit]\niters_t0 = " + "[" * 100_000 + "]" * 100_000 + "\n")
    run = subprocess.run([sys.executable, "-m", "odsplat", "config", str(bare.root), "--config", str(path)],
                         capture_output=True, text=True, cwd=REPO, timeout=30)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.strip() == f"odsplat: error: {path}: not TOML odsplat can read: nested too deep"


@pytest.mark.timeout(30)
@pytest.mark.parametrize("args, names", [
    (["magnify", "{cap}", "--alpha", "1e308"], "MagnifySettings.alpha"),
    (["magnify", "{cap}", "--workers", "1000000"], "MagnifySettings.workers"),
    (["magnify", "{cap}", "--option", "n_orientations=" + "[" * 50_000], "MagnifySettings.options.n_orientations"),
    (["sync", "{cap}", "--workers", "1000000"], "SyncSettings.workers"),
    (["reconstruct", "{cap}", "--width", "100000000"], "ReconstructSettings.width_px"),
    (["reconstruct", "{cap}", "--iters-t0", str(10 ** 18)], "FitSettings.iters_t0"),
    (["reconstruct", "{cap}", "--threads", "100000"], "ReconstructSettings.threads"),
    (["analyze", "{cap}", "--max-order", str(10 ** 12)], "AnalyzeSettings.max_order"),
    (["analyze", "{cap}", "--fmax", "1e308"], "AnalyzeSettings.fmax_hz"),
    (["render", "{cap}", "--alpha", "1e308"], "--alpha: expected a finite number >= 0 and <= 10000"),
    (["render", "{cap}", "--width", "100000000"], "--width: expected an integer >= 8 and <= 16384"),
    (["render", "{cap}", "--fps", "1e9"], "--fps"),
    (["view", "{cap}", "--alpha", "1e308"], "--alpha: expected a finite number >= 1 and <= 1000"),
    (["view", "{cap}", "--frames", "1000000000"], "--frames"),
    (["view", "{cap}", "--fps", "inf"], "--fps"),
    (["export-video", "{cap}", "--fps", "1e9"], "--fps: expected a finite number >= 0.1 and <= 1000"),
    (["batch", "{cap}", "--workers", "100000"], "--workers: expected an integer >= 1 and <= 1024"),
    (["run", "{cap}", "--set", "reconstruct.fit.iters_t0=1e18"], "reconstruct.fit.iters_t0: expected an integer"),
])
def test_each_command_refuses_an_abusive_option_before_it_starts(bare, args, names):
    before = _files(bare.root)
    r = CliRunner().invoke(main, [a.replace("{cap}", str(bare.root)) for a in args])
    lines = r.output.strip().splitlines()
    assert r.exit_code == 2 and lines and lines[-1].startswith("odsplat: error: "), r.output[-3000:]
    assert names in lines[-1] and len(lines[-1]) < LONGEST_LINE and "Traceback" not in r.output
    assert _files(bare.root) == before, "something was written"
