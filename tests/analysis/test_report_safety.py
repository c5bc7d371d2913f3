"""The HTML report is safe to mail: nothing from analysis.json reaches the page as markup, whatever a hand-edited
file holds (its text shows as text; a field of the wrong kind is refused in one line naming it), and only the files
the analysis wrote in derived/analysis/ are inlined."""
from __future__ import annotations

import base64
import io
import json
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from odsplat.analysis.report import render_video, write_report
from odsplat.spine.contract import describe
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import Manifest
from odsplat.spine.store import Capture

PAYLOADS = ("<script>alert(1)</script>", '"><img src=x onerror=alert(1)>')
# The header's text, checked before anything is read: poisoned, the report is refused; `files` is poisoned apart.
CHECKED = {".kind", ".capture_id", ".files"}
# Text fields the page shows as they are: each must appear, escaped, as the page's text.
SHOWN = (".capture", ".created_utc", ".notes[0]", ".takes[0]", ".rejected_hits[0].take",
         ".rejected_hits[0].reasons[0]", ".rejected_hits[1].reasons[0]", ".sensors[0]", ".video.structure_rule",
         ".video.crosscheck[0].take", ".video.crosscheck_verdict.status", ".video.crosscheck_verdict.line",
         ".correlation.verdict.status", ".correlation.verdict.line", ".settings.response_channels[0]")
PAGE_TAGS = {"html", "head", "meta", "title", "style", "body", "h1", "h2", "h3", "p", "b", "ul", "li", "table", "tr",
             "th", "td", "span", "figure", "img", "figcaption", "details", "summary", "pre", "section", "div"}
IMAGE_SRC = re.compile(r"data:image/(png|gif|webp);base64,[A-Za-z0-9+/=]+")


def _png(path: Path, level: int) -> bytes:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((12, 16, 3), level, np.uint8)).save(path, format="PNG")
    return path.read_bytes()


def _gif(path: Path, level: int) -> bytes:
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = [Image.fromarray(np.full((12, 16), (level + 40 * k) % 256, np.uint8)) for k in range(3)]
    frames[0].save(path, format="GIF", save_all=True, append_images=frames[1:])
    return path.read_bytes()


def _analysis(capture: Capture) -> dict:
    """An analysis.json holding every field the report reads, as `odsplat analyze` writes them."""
    return {**describe(capture.id, "odsplat.analysis", 2, {}).header(), "capture": "bench-arm",
            "created_utc": "2024-05-01T10:00:00Z", "settings": {"fmax_hz": 450.0, "response_channels": ["acc_tip_z"]},
            "takes": ["t1", "t2", "t3"], "n_averages": 2,
            "rejected_hits": [{"take": "t2", "reasons": ["double hit at +2.1 ms"]},
                              {"take": "t9", "reasons": ["late"]}],
            "sensors": ["tip z", "tip y"], "exp_tau_s": 0.003,
            "modes": [{"freq_hz": 23.5, "damping": 0.01}, {"freq_hz": 31.0, "damping": 0.012},
                      {"freq_hz": 86.0, "damping": 0.008}],
            "band_hz": [5.0, 450.0], "notes": ["mode 3 (86.0 Hz): below the video's noise floor"],
            "video": {"modes_fitted": [0, 1, 2], "sensor_r2": [0.97, 0.95], "condition": 4.2,
                      "freq_hz": [23.6, 48.9], "damping": [0.01, 0.02], "window_s": [0.0015, 0.0115],
                      "n_surface_points": 4000, "shapes_from": "measured", "n_background_points": 1500,
                      "structure_rule": "above the floor", "background_rms_um": 5.1, "background_amplitude_um": 0.8,
                      "background_amplitude_ratio": 0.04, "background_amplitude_ratio_all": 0.05,
                      "n_background_reference_points": 600,
                      "crosscheck": [{"take": "v00_000", "n_points": 120, "gain": 0.98, "correlation": 0.97,
                                      "motion_rms_px": 0.4, "residual_rms_px": 0.05, "force_ratio": 1.01,
                                      "noise_px": 0.01}],
                      "noise_floor": {"sigma_um": 5.0, "static_sigma_um": 4.8, "n_static_points": 300,
                                      "pre_impact_sigma_um": 5.2, "n_pre_impact": 4, "sensor_sigma_um": [5.1, 4.9],
                                      "point_sigma_um_p10_p90": [4.0, 6.5], "floor_sigmas": 3.0, "floor_mac": 0.9,
                                      "modes": [{"freq_hz": f, "amplitude_um": a, "floor_um": 15.0,
                                                 "spectrum_gain": 1.0, "below_floor": a < 15.0}
                                                for f, a in ((23.5, 120.0), (31.0, 80.0), (86.0, 4.0))]},
                      "real_modes": [{"freq_hz": 23.5, "mpc": 0.999, "quadrature_over_noise": 1.1, "lost": 0.01,
                                      "real": True},
                                     {"freq_hz": 31.0, "mpc": 0.9, "quadrature_over_noise": 6.0, "lost": 0.2,
                                      "real": False}],
                      "crosscheck_verdict": {"status": "met", "line": "gain 0.98, correlation 0.97"}},
            "image_poles": {"freq_hz": [23.4, 31.1], "damping": [0.01, 0.011], "n_views": 3, "n_pixels": 5000,
                            "window_s": [0.001, 0.02], "component_snr": [10.0, 5.0]},
            "correlation": {"pairs": [{"a": 0, "b": 0, "mac": 0.99, "scale_factor_abs": 1.02,
                                       "scale_factor_phase_deg": 3.0, "freq_a_hz": 23.5, "freq_b_hz": 23.6,
                                       "freq_diff_rel": 0.004, "video_amplitude_um": 120.0, "noise_floor_um": 15.0,
                                       "below_noise_floor": False, "expected_mac": 0.98},
                                      {"a": 2, "b": 2, "mac": 0.7, "scale_factor_abs": 0.9,
                                       "scale_factor_phase_deg": -8.0, "freq_a_hz": 86.0, "freq_b_hz": 86.4,
                                       "freq_diff_rel": 0.005, "video_amplitude_um": 4.0, "noise_floor_um": 15.0,
                                       "below_noise_floor": True, "expected_mac": 0.07}],
                            "comac": [0.98, 0.97], "verdict": {"status": "met", "line": "MAC >= 0.9 for all 2 modes"}},
            "ods": [{"freq_hz": 23.5, "mac": 0.99}],
            "files": {"frf": "plots/frf.png", "anim_01": "plots/anim_01.gif", "results": "results.h5"}}


def _capture(root: Path) -> Capture:
    """A capture whose derived/analysis/ holds a plot and an animation, as the analysis writes them."""
    capture = Capture(root, Manifest(name="bench-arm"))
    _png(capture.paths.analysis_dir / "plots" / "frf.png", 90)
    _gif(capture.paths.analysis_dir / "plots" / "anim_01.gif", 10)
    return capture


def _poisoned(x, payload: str, path: str = ""):
    """x with every text the report may show replaced by `payload` and the text's path, but for the header's
    (CHECKED); the keys of `settings`, which the page shows too, get theirs. Numbers and flags stay: one of the
    wrong kind is refused (tests/analysis/test_document.py)."""
    if isinstance(x, dict):
        out = {}
        for k, v in x.items():
            p = f"{path}.{k}"
            if p in CHECKED:
                out[k] = v
            else:
                out[f"{payload} {p}#key" if path == ".settings" else k] = _poisoned(v, payload, p)
        return out
    if isinstance(x, list):
        return [_poisoned(v, payload, f"{path}[{i}]") for i, v in enumerate(x)]
    return f"{payload} {path}" if isinstance(x, str) else x


class _Page(HTMLParser):
    """The page as a browser sees it: its tags with their attributes, and its text with the entities read."""

    def __init__(self, html: str):
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, dict]] = []
        self.texts: list[str] = []
        self.feed(html)
        self.close()

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.texts.append(data)


def _assert_inert(html: str) -> _Page:
    """No element, attribute or URL on the page but those the templates write (a payload's `onerror=` may stand
    in the text or inside an attribute's value, escaped, never as an attribute)."""
    assert "<script" not in html.lower() and "<img src=x" not in html
    page = _Page(html)
    assert {tag for tag, _ in page.tags} <= PAGE_TAGS, {tag for tag, _ in page.tags} - PAGE_TAGS
    for tag, attrs in page.tags:
        assert not [a for a in attrs if a.startswith("on")], (tag, attrs)
        if tag == "img":
            assert IMAGE_SRC.fullmatch(attrs["src"] or ""), attrs["src"][:80]
    return page


@pytest.mark.parametrize("payload", PAYLOADS)
def test_every_field_of_analysis_json_is_shown_as_text(tmp_path, payload):
    capture = _capture(tmp_path / "cap")
    doc = _poisoned(_analysis(capture), payload)
    doc["files"] = {"frf": f"{payload} .files.frf.png", "up": f"../{payload} .files.up.png",
                    f"{payload} .files#key": "plots/frf.png", f"{payload} .files#key_01": "plots/anim_01.gif"}
    capture.paths.analysis_json.write_text(json.dumps(doc))
    html = write_report(capture).read_text()
    page = _assert_inert(html)
    text = "".join(page.texts)
    for path in SHOWN:
        assert f"{payload} {path}" in text, path
    # a file name that names no file, or none the analysis wrote, is said so, as text
    assert f"{payload} .files.frf.png not found." in text
    assert f"../{payload} .files.up.png: not a file the analysis wrote (outside derived/analysis)" in text
    # the names of the files it did write are the images' alt text, whole
    alts = {attrs["alt"] for tag, attrs in page.tags if tag == "img"}
    assert alts == {f"{payload} .files#key", f"{payload} .files#key_01"}
    assert f"{payload} .settings.fmax_hz#key" in text


def test_the_crosschecks_point_count_is_refused_as_text(tmp_path):
    """The leak first reported: a number the report showed as it stood in the file (issue 41). A number that is
    text now stops the report in one line naming it; one that is no finite number shows as a dash."""
    capture = _capture(tmp_path / "cap")
    doc = _analysis(capture)
    doc["video"]["crosscheck"][0]["n_points"] = PAYLOADS[0]
    capture.paths.analysis_json.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        write_report(capture)
    assert err.value.source == f"{capture.paths.analysis_json}: video.crosscheck[0].n_points"
    assert err.value.problem.startswith("expected an integer; got '<script>")
    assert "\n" not in str(err.value) and not capture.paths.report_html.exists()
    doc["video"]["crosscheck"][0].update(n_points=120, gain=float("nan"))
    capture.paths.analysis_json.write_text(json.dumps(doc))
    html = write_report(capture).read_text()
    _assert_inert(html)
    assert "<td>v00_000</td><td>120</td><td>\u2013</td><td>0.97</td>" in html.replace('<td class="t">', "<td>")


@pytest.mark.parametrize("field", [("modes", 0, "freq_hz"), ("modes", 1, "damping"), ("kind",),
                                   ("video", "noise_floor", "sigma_um"), ("correlation", "pairs", 1, "b")])
def test_a_poisoned_field_the_report_needs_is_refused_by_name(tmp_path, field):
    capture = _capture(tmp_path / "cap")
    doc = _analysis(capture)
    *outer, last = field
    target = doc
    for k in outer:
        target = target[k]
    target[last] = PAYLOADS[0]
    capture.paths.analysis_json.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        write_report(capture)
    name = "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in field)[1:]
    assert (err.value.source == f"{capture.paths.analysis_json}: {name}" if len(field) > 1
            else "not an odsplat.analysis file" in err.value.problem)
    assert "\n" not in str(err.value) and not capture.paths.report_html.exists()


def test_only_the_files_the_analysis_wrote_are_inlined(tmp_path):
    """A `files` entry that leads out of derived/analysis (up, absolute, through a link to a file or a folder) is
    not read: the outside file's bytes are nowhere in the page, and one line says why."""
    capture = _capture(tmp_path / "cap")
    folder = capture.paths.analysis_dir
    secret_png = _png(tmp_path / "secret.png", 250)
    secret_gif = _gif(tmp_path / "secret.gif", 200)
    _png(tmp_path / "elsewhere" / "frf.png", 250)
    (tmp_path / "cap" / "capture.json").write_text('{"name": "the capture file, not a plot"}')
    (folder / "plots" / "link.png").symlink_to(tmp_path / "secret.png")
    (folder / "plots" / "anim_02.gif").symlink_to(tmp_path / "secret.gif")
    (folder / "linked").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    files = {"frf": "plots/frf.png", "up": "../../../secret.png", "dots": "plots/../../../../secret.png",
             "absolute": str(tmp_path / "secret.png"), "link": "plots/link.png", "folder": "linked/frf.png",
             "capture": "../../capture.json", "anim_01": "plots/anim_01.gif", "anim_02": "plots/anim_02.gif",
             "anim_03": str(tmp_path / "secret.gif")}
    capture.paths.analysis_json.write_text(json.dumps({**_analysis(capture), "files": files}))
    html = write_report(capture).read_text()
    _assert_inert(html)
    for secret in (secret_png, secret_gif, (tmp_path / "cap" / "capture.json").read_bytes()):
        assert base64.b64encode(secret).decode() not in html
    assert "the capture file" not in html
    own = base64.b64encode((folder / "plots" / "frf.png").read_bytes()).decode()
    assert re.findall(r'src="data:image/png;base64,([^"]+)"', html) == [own]
    assert len(re.findall(r'src="data:image/gif;base64,', html)) == 1
    outside = "not a file the analysis wrote (outside derived/analysis)"
    for rel in ("../../../secret.png", "plots/../../../../secret.png", str(tmp_path / "secret.png"),
                str(tmp_path / "secret.gif")):
        assert f'<p class="bad">{rel}: {outside}</p>' in html, rel
    for rel in ("plots/link.png", "linked/frf.png", "plots/anim_02.gif"):
        assert f'<p class="bad">{rel}: not a file the analysis wrote (a symbolic link)</p>' in html, rel


def test_a_file_of_the_wrong_kind_is_not_inlined(tmp_path):
    capture = _capture(tmp_path / "cap")
    (capture.paths.analysis_dir / "plots" / "notes.png").write_text("<script>alert(1)</script>")
    files = {"frf": "plots/frf.png", "notes": "plots/notes.png"}
    capture.paths.analysis_json.write_text(json.dumps({**_analysis(capture), "files": files}))
    html = write_report(capture).read_text()
    _assert_inert(html)
    assert '<p class="bad">plots/notes.png: not a PNG image</p>' in html
    assert len(re.findall(r'src="data:image/png;base64,', html)) == 1


def test_the_render_reads_only_its_own_frames(tmp_path):
    render = tmp_path / "render"
    _png(render / "frame_0000.png", 40)
    _png(tmp_path / "secret.png", 250)
    (render / "frame_0001.png").symlink_to(tmp_path / "secret.png")
    html = render_video(render)
    im = Image.open(io.BytesIO(base64.b64decode(re.search(r'src="data:image/webp;base64,([^"]+)"', html).group(1))))
    assert im.n_frames == 1
    assert "frame_0001.png: not a file `odsplat render` wrote (a symbolic link)" in html
