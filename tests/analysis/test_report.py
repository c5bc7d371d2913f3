"""The analysis figures and the HTML report, on an AnalysisResult built from the simulated structure's analytic FRFs,
modes fitted by fit_modes, and a synthetic video side with the analytic 3D residues."""
from __future__ import annotations

import base64
import dataclasses
import json
import re

import numpy as np
import pytest
from PIL import Image

from odsplat.analysis import read_analysis
from odsplat.analysis.correlation import correlate
from odsplat.analysis.ema import fit_modes
from odsplat.analysis.frf import FRFResult, HitCheck
from odsplat.analysis.ods import receptance
from odsplat.analysis.plots import ODS_SCALE, plot_frf, plot_mac, plot_ods, write_plots
from odsplat.analysis.report import write_report
from odsplat.analysis.result import AnalysisResult, Sensor, VideoModes
from odsplat.hil_sim.structure import ModalStructure
from odsplat.spine.contract import describe
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import Manifest
from odsplat.spine.store import Capture

STRUCTURE = ModalStructure()
FREQ_HZ = np.arange(1001) * 0.5  # 0-500 Hz
HAMMER = ((0.46, 0.03, 0.60), np.array([1.0, 1.0, -1.0]) / np.sqrt(3))
SENSORS = (Sensor("tip z", np.array([0.43, 0.0, 0.60]), np.array([0.0, 0.0, 1.0])),
           Sensor("tip y", np.array([0.43, 0.03, 0.57]), np.array([0.0, 1.0, 0.0])),
           Sensor("column x", np.array([0.045, 0.0, 0.40]), np.array([1.0, 0.0, 0.0])),
           Sensor("column y", np.array([0.0, 0.045, 0.50]), np.array([0.0, 1.0, 0.0])))
N_VIDEO_MODES = 4  # the camera's band holds the four lowest modes
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _hit(accepted: bool, reasons=()) -> HitCheck:
    return HitCheck(accepted, tuple(reasons), 200.0, 10.0, 30.0, 1e-3, 1 + (not accepted), 0.0)


def _surface_points(n: int, seed: int = 0) -> np.ndarray:
    """Random points on the faces of the column's and the arm's boxes."""
    rng = np.random.default_rng(seed)
    boxes = [STRUCTURE.geometry.boxes()[k] for k in ("column", "arm")]
    pts = []
    for i in range(n):
        lo, hi = boxes[i % 2]
        p = lo + rng.random(3) * (hi - lo)
        axis = rng.integers(3)
        p[axis] = (lo if rng.random() < 0.5 else hi)[axis]
        pts.append(p)
    return np.array(pts)


def _residues(points, dirs=None) -> np.ndarray:
    """Analytic displacement residues A_r = phi_out phi_in / (2 i w_d): (R, P, 3), or (R, P) along dirs."""
    phi = STRUCTURE.mode_shapes(points)                                    # (P, R, 3)
    if dirs is not None:
        phi = np.einsum("prc,pc->pr", phi, dirs)
    phi_in = STRUCTURE.participation(*HAMMER)
    wd = 2 * np.pi * STRUCTURE.freqs_hz * np.sqrt(1 - STRUCTURE.dampings**2)
    return np.moveaxis(phi, 1, 0) * (phi_in / (2j * wd)).reshape((-1,) + (1,) * (phi.ndim - 1))


@pytest.fixture(scope="module")
def result() -> AnalysisResult:
    h1 = np.stack([STRUCTURE.frf(s.position_m, s.direction, *HAMMER, FREQ_HZ, kind="accelerance")
                   for s in SENSORS], axis=1)
    coherence = np.ones(h1.shape)
    coherence[FREQ_HZ > 450] = 0.7
    frf = FRFResult(FREQ_HZ, h1, h1, coherence, np.ones(len(FREQ_HZ)), np.abs(h1), "hammer",
                    tuple(s.name for s in SENSORS), "m/s^2", 1000.0, 1000, 3,
                    (_hit(True), _hit(False, ["double hit at +2.1 ms (35 % of the peak)"]), _hit(True), _hit(True)),
                    None, 3e-3)
    modes = fit_modes(FREQ_HZ, h1, frf_kind="accelerance", fmin_hz=5, fmax_hz=450, max_order=40,
                      approx_freq_hz=STRUCTURE.freqs_hz, output_names=frf.output_names)
    assert modes.n_modes == 6
    idx = np.arange(N_VIDEO_MODES)
    pos = np.stack([s.position_m for s in SENSORS])
    dirs = np.stack([s.direction for s in SENSORS])
    pts = _surface_points(4000)
    rng = np.random.default_rng(1)
    true = _residues(pos, dirs)[idx]
    sensor_res = true + 0.2 * np.abs(true).max(axis=1, keepdims=True) * rng.standard_normal(true.shape)
    t = np.arange(200) / 2000.0
    lam = modes.poles_rad_s[idx]
    disp = 2 * (np.exp(np.outer(t, lam)) @ sensor_res).real * 0.2       # 0.2 N s impulse
    video = VideoModes(lam, idx, sensor_res, pts, _residues(pts)[idx], np.full(len(SENSORS), 0.97), 4.2,
                       STRUCTURE.freqs_hz[:3] * 1.01, STRUCTURE.dampings[:3], t, disp)
    corr = correlate(modes.shapes[idx], sensor_res, freq_a_hz=modes.freq_hz[idx], freq_b_hz=video.freq_hz[[0, 1, 2, 2]])
    rec = frf.to_receptance()
    lines = np.searchsorted(FREQ_HZ, modes.freq_hz)
    return AnalysisResult(frf, modes, SENSORS, ("t1", "t2", "t3", "t4"), video, corr, modes.freq_hz,
                          rec.h1[lines], receptance(sensor_res, lam, modes.freq_hz),
                          receptance(video.surface_residues, lam, modes.freq_hz))


@pytest.fixture(scope="module")
def written(result, tmp_path_factory):
    dest = tmp_path_factory.mktemp("capture") / "derived" / "analysis"
    return dest, write_plots(dest, result)


def test_write_plots_writes_every_figure_as_a_png(written, result):
    dest, files = written
    ods = {f"ods_{i + 1:02d}" for i in range(len(result.ods_freq_hz))}
    anims = {f"anim_{k + 1:02d}" for k in range(result.modes.n_modes)}
    assert set(files) == {"frf", "stabilisation", "automac", "mac", "time", "shapes3d"} | ods | anims
    for key in anims:
        with Image.open(dest / files[key]) as im:
            assert files[key] == f"plots/{key}.gif" and im.format == "GIF" and im.n_frames == 12
    for key, rel in files.items():
        if key in anims or key == "shapes3d":
            continue
        path = dest / rel
        assert rel == f"plots/{key}.png" and path.is_file()
        assert path.read_bytes()[:8] == PNG_SIGNATURE
        assert path.stat().st_size > 10_000, (key, path.stat().st_size)
        with Image.open(path) as im:
            assert im.format == "PNG" and min(im.size) >= 300, (key, im.size)


def test_plot_mac_prints_the_values():
    fig = plot_mac(np.eye(3), ["a1", "a2", "a3"], ["b1", "b2", "b3"])
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts.count("1.00") == 3 and texts.count("0.00") == 6


def test_plot_ods_scales_the_largest_displacement_to_a_tenth_of_the_size(result):
    fig = plot_ods(result, 0)
    ax = fig.axes[0]
    rest, moved = (np.column_stack(c._offsets3d) for c in ax.collections[:2])
    every = np.concatenate([rest, np.stack([s.position_m for s in SENSORS])])
    size = np.linalg.norm(np.ptp(every, axis=0))
    assert np.max(np.linalg.norm(moved - rest, axis=1)) == pytest.approx(ODS_SCALE * size, rel=1e-6)
    assert len(rest) == 3000 and f"{result.ods_freq_hz[0]:.2f} Hz" in ax.get_title()


def test_plots_without_video_nan_lines_and_one_sensor(result, tmp_path):
    frf = result.frf
    one = dataclasses.replace(frf, h1=frf.h1[:, :1].copy(), h2=frf.h2[:, :1], coherence=frf.coherence[:, :1],
                              output_names=frf.output_names[:1])
    one.h1[100:120] = np.nan
    assert len(plot_frf(one, result.modes).axes) == 3
    bare = dataclasses.replace(result, video=None, correlation=None, ods_video=np.zeros((0, 0), complex))
    files = write_plots(tmp_path, bare)
    assert {"frf", "stabilisation", "ods_01"} <= set(files) and not {"mac", "time"} & set(files)
    assert len(plot_ods(bare, 2).axes[0].collections) >= 1
    with pytest.raises(InputError, match="line_index"):
        plot_ods(bare, 99)


def _document(result: AnalysisResult, capture: Capture, files: dict[str, str]):
    return result.document(describe(capture.id, "odsplat.analysis", 2, {}), capture="bench-arm",
                           created_utc="2024-05-01T10:00:00Z", settings={"fmax_hz": 450.0}, files=files)


def test_report_embeds_the_numbers_and_figures(written, result):
    dest, files = written
    capture = Capture(dest.parent.parent, Manifest(name="bench-arm"))
    document = _document(result, capture, {**files, "results": "results.h5"})
    assert document.write(capture) == dest / "analysis.json"
    assert read_analysis(capture) == document                          # it reads back as written
    html = write_report(capture).read_text()
    for f, z in zip(result.modes.freq_hz, result.modes.damping):
        assert f"<td>{f:.2f}</td><td>{100 * z:.2f}</td>" in html
    assert "<td>23.50</td><td>1.00</td>" in html                      # the structure's first mode, 1 % damping
    for m in result.correlation.pair_mac:
        assert f"<td>{m:.3f}</td>" in html
    assert "double hit at +2.1 ms" in html and "3 of 4 hits used" in html
    imgs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html)
    assert len(imgs) == len([f for f in files.values() if f.endswith(".png")])
    # each mode the video fitted in 3D (data for the page's plotly), the others as the accelerometers' GIF
    n_3d = len(result.video.mode_index)
    assert html.count('<div class="shape3d" data-mode=') == n_3d and 'id="shapes3d-data"' in html
    assert len(re.findall(r'<img src="data:image/gif;base64,', html)) == result.modes.n_modes - n_3d
    assert all(base64.b64decode(b)[:8] == PNG_SIGNATURE for b in imgs)
    assert "bench-arm" in html and "2024-05-01" in html


def _header(capture: Capture) -> dict:
    return describe(capture.id, "odsplat.analysis", 2, {}).header()


def test_report_input_errors(tmp_path, result):
    capture = Capture(tmp_path, Manifest(name="cap"))
    path = tmp_path / "derived" / "analysis" / "analysis.json"
    with pytest.raises(InputError, match="odsplat analyze") as err:
        write_report(capture)
    assert err.value.source == str(path)
    path.parent.mkdir(parents=True)
    path.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        write_report(capture)
    path.write_text(json.dumps({"modes": [{"freq_hz": 23.5, "damping": 0.01}]}))
    with pytest.raises(InputError, match="not an odsplat.analysis file"):
        write_report(capture)
    path.write_text(json.dumps({**_header(Capture(tmp_path, Manifest(name="other"))), "modes": []}))
    with pytest.raises(InputError, match="belongs to another capture"):
        write_report(capture)
    doc = _document(result, capture, {}).to_json()
    del doc["modes"][0]["freq_hz"]
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        write_report(capture)
    assert err.value.source == f"{path}: modes[0].freq_hz" and err.value.problem == "missing"


def test_the_render_plays_inline_when_there_is_one(tmp_path):
    import io

    from odsplat.analysis.report import render_video

    assert render_video(tmp_path) == ""
    for k in range(5):
        Image.fromarray(np.full((300, 400, 3), 40 * k, np.uint8)).save(tmp_path / f"frame_{k:04d}.png")
    html = render_video(tmp_path)
    data = re.search(r'<img src="data:image/webp;base64,([^"]+)"', html).group(1)
    im = Image.open(io.BytesIO(base64.b64decode(data)))
    assert im.format == "WEBP" and im.n_frames == 5 and im.size == (400, 300)
    # with the render's mp4 beside the frames (as `odsplat render` writes it), the page plays the mp4 itself
    import av

    from odsplat.spine.mp4 import write_mp4

    write_mp4(tmp_path / "render.mp4", [np.full((300, 400, 3), 40 * k, np.uint8) for k in range(5)], 10.0)
    html = render_video(tmp_path)
    data = re.search(r'<video src="data:video/mp4;base64,([^"]+)" controls', html).group(1)
    assert base64.b64decode(data) == (tmp_path / "render.mp4").read_bytes() and "image/webp" not in html
    with av.open(io.BytesIO(base64.b64decode(data))) as container:
        assert container.streams.video[0].codec_context.name == "h264"


def test_a_camera_pole_off_every_mode_is_said_to_be_none_and_named_near_the_strongest_motions_products():
    """A video pole 4 % from twice the strongest mode (the demo's 48.9 Hz beside 2 x 23.5 Hz) is no accelerometer
    mode, and lies where the image's slight nonlinearity in the strongest motion puts energy; a pole on a mode is
    neither."""
    from odsplat.analysis.document import ModeEntry, PairEntry
    from odsplat.analysis.report import _poles_table

    modes = tuple(ModeEntry(f, 0.01) for f in (23.5, 31.0, 86.0, 142.0))
    pairs = tuple(PairEntry(a=k, b=k, mac=0.99, scale_factor_abs=1.0, scale_factor_phase_deg=0.0, video_amplitude_um=a)
                  for k, a in enumerate((120.0, 80.0, 30.0, 4.0)))
    html = _poles_table(modes, (23.49, 48.9, 141.4, 300.0), (0.01,) * 4, "Poles", "none", pairs)
    rows = re.findall(r"<tr>(.*?)</tr>", html)[1:]
    assert "no accelerometer mode" not in rows[0] and "no accelerometer mode" not in rows[2]
    assert "no accelerometer mode within 1 %; near 2 x mode 1 (47.0 Hz)" in rows[1], rows[1]
    assert "no accelerometer mode within 1 %" in rows[3] and "; near" not in rows[3]


def test_sensors_at_one_place_are_named_in_one_label():
    """A triaxial block's channels sit within millimetres: their names share one label in the ODS figures, instead
    of printing over one another."""
    from odsplat.analysis import Sensor
    from odsplat.analysis.plots import _sensor_labels

    tip = np.array([0.5, 0.0, 0.6])
    sensors = [Sensor("tip_z", tip, np.array([0, 0, 1.0])), Sensor("tip_y", tip + [0, 0.002, 0], np.array([0, 1, 0.0])),
               Sensor("col_x", np.array([0, 0, 0.3]), np.array([1, 0, 0.0])), Sensor("unplaced")]
    labels = _sensor_labels(sensors, apart_m=0.009)
    assert [names for _, names in labels] == ["tip_z, tip_y", "col_x"]
    assert np.array_equal(labels[0][0], tip)
