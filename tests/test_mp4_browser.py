"""The project's mp4s play in a browser: `odsplat.spine.mp4` writes H.264 in yuv420p (decoded back here with PyAV,
frames, size and rate), and where Chromium is installed, headless Chromium plays one (the MPEG-4 Part 2 'mp4v'
files OpenCV wrote before failed there with DEMUXER_ERROR_NO_SUPPORTED_STREAMS, MediaError 4)."""
from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest

from odsplat.spine.errors import InputError
from odsplat.spine.mp4 import Mp4Writer, codec, count_frames, read_comment, write_mp4

from .browser import chromium, page_title


def _frames(n: int, height: int, width: int, rgb: bool = True) -> list[np.ndarray]:
    """A moving pattern: every frame differs, so the encoder makes P and B frames."""
    y, x = np.mgrid[0:height, 0:width]
    out = []
    for i in range(n):
        grey = ((x * 5 + y * 3 + i * 8) % 256).astype(np.uint8)
        out.append(np.stack([grey, (y * 7 % 256).astype(np.uint8), np.full_like(grey, 128)], -1) if rgb else grey)
    return out


def _decoded(path: Path) -> tuple[str, str, int, int, Fraction, list[np.ndarray]]:
    """(codec, pixel format, width, height, average rate, luma planes) as PyAV decodes them."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray()[:f.height] for f in container.decode(stream)]   # yuv420p: Y's rows come first
        cc = stream.codec_context
        return cc.name, cc.pix_fmt, stream.width, stream.height, stream.average_rate, frames


@pytest.mark.parametrize("n, height, width, fps, rgb", [
    (20, 64, 96, 29.97, True),        # NTSC's rate as a float
    (12, 33, 47, 2000 / 64, False),   # odd size (padded to 48x34), a slow-motion rate
    (1, 32, 32, 30.0, True),          # the smallest useful video: one tiny frame
])
def test_written_mp4_decodes_as_h264_yuv420p(tmp_path, n, height, width, fps, rgb):
    frames = _frames(n, height, width, rgb)
    info = write_mp4(tmp_path / "v.mp4", frames, fps, comment="odsplat test ©")
    name, pix_fmt, w, h, rate, decoded = _decoded(info.path)
    even = (width + width % 2, height + height % 2)
    assert codec() == info.codec == "h264" and name == "h264" and pix_fmt == "yuv420p"
    assert (info.width_px, info.height_px) == (w, h) == even
    assert info.n_frames == len(decoded) == count_frames(info.path) == n
    assert rate == Fraction(fps).limit_denominator(10_000)
    assert read_comment(info.path) == "odsplat test ©"
    for got, want in zip(decoded, frames):   # BT.709 luma in limited range (16-235), the padding a copy of the edge
        luma = want if want.ndim == 2 else want @ np.array([0.2126, 0.7152, 0.0722])
        padded = np.pad(16 + luma * (219 / 255), ((0, even[1] - height), (0, even[0] - width)), mode="edge")
        assert np.abs(got - padded).mean() < 2.0                     # measured 0.9-1.2
        assert np.abs(got[-1] - padded[-1]).mean() < 10.0             # the last row and column: copies (measured
        assert np.abs(got[:, -1] - padded[:, -1]).mean() < 10.0       # <= 4.7), where black ones would be ~100 off


def test_no_file_without_a_clean_close(tmp_path):
    path = tmp_path / "v.mp4"
    with pytest.raises(RuntimeError), Mp4Writer(path, 30.0) as writer:
        writer.write(_frames(1, 32, 32)[0])
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="a frame of 30x32 px in a video of 32x32 px"), Mp4Writer(path, 30.0) as w:
        w.write(_frames(1, 32, 32)[0])
        w.write(_frames(1, 32, 30)[0])
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="outside what the mp4 writer takes"):
        Mp4Writer(path, 1e-5)


def test_a_comment_set_before_close_is_written(tmp_path):
    """magnify knows its comment (the DN mapping) only after the frames: the writer takes it until close()."""
    with Mp4Writer(tmp_path / "v.mp4", 25.0) as writer:
        for frame in _frames(50, 32, 48, rgb=False):   # past x264's lookahead: packets are muxed before the end
            writer.write(frame)
        writer.comment = "recorded at 2000 frames/s, played at 25 frames/s"
    assert read_comment(tmp_path / "v.mp4") == "recorded at 2000 frames/s, played at 25 frames/s"
    assert count_frames(tmp_path / "v.mp4") == 50


_PAGE = """<!doctype html><html><head><title>WAITING</title></head><body>
<video id="v" muted playsinline preload="auto" src="{src}"></video>
<script>
const v = document.getElementById("v");
const say = (s) => {{ document.title = s; document.body.setAttribute("data-result", s); }};
v.addEventListener("error", () => say("ERROR " + (v.error ? v.error.code + " " + v.error.message : "unknown")));
v.addEventListener("canplay", () => {{ v.play().catch((e) => say("PLAYFAIL " + e.name + " " + e.message)); }});
v.addEventListener("timeupdate", () => {{
  if (v.currentTime > 0) say("PLAYED " + v.videoWidth + "x" + v.videoHeight);
}});
</script></body></html>
"""


def _chromium() -> str | None:
    return chromium()


@pytest.mark.skipif(_chromium() is None, reason="no chromium, chromium-browser or google-chrome on PATH: the "
                                                "browser check needs one (the decode test above still runs)")
def chromium_plays(video: Path, folder: Path) -> str:
    """What headless Chromium says of `video` played in a page written in `folder` (_PAGE's title: "PLAYED WxH",
    "ERROR code message", ...), or why it said nothing. Only where `_chromium()` finds one."""
    page = folder / "play.html"
    page.write_text(_PAGE.format(src=video.resolve().as_uri()))
    title, run = page_title(page, folder, "--autoplay-policy=no-user-gesture-required",
                            "--allow-file-access-from-files", budget_ms=10000, timeout_s=60)
    return title if title is not None else f"no page dumped (exit {run.returncode}): {run.stderr[-1500:]}"


def test_headless_chromium_plays_the_mp4(tmp_path):
    info = write_mp4(tmp_path / "clip.mp4", _frames(30, 45, 61), 29.97, comment="browser check")
    result = chromium_plays(info.path, tmp_path)
    assert result == f"PLAYED {info.width_px}x{info.height_px}" == "PLAYED 62x46", result


def test_every_mp4_the_pipeline_writes_plays_in_chromium(piped_original, tmp_path):
    """magnify's mp4 of the view to watch, export-video's of a raw take, the render's, the viewer's export and the
    report's mode clip (the 2D path's clips: tests/test_video2d.py) each load into a <video> of one page in
    headless Chromium, with the duration and size their files hold."""
    from click.testing import CliRunner

    from odsplat.app.cli import main

    from .browser import video_durations
    from .conftest import piped_copy

    cap = piped_copy(piped_original, tmp_path / "copy" / "cap")
    videos = sorted((cap / "derived" / "magnified").rglob("*.mp4"))
    assert videos, "magnify wrote no mp4"
    runner = CliRunner()
    take = sorted(p.name.split(".")[0] for p in (cap / "takes").glob("*.h5"))[0]
    for args in (["export-video", str(cap), "--take", take, "-o", str(tmp_path / "raw.mp4")],
                 ["render", str(cap), "--width", "64", "--times", "0:0.006:6", "-o", str(tmp_path / "render")],
                 ["view", str(cap), "--export", str(tmp_path / "view.mp4"), "--frames", "8"],
                 ["report", str(cap), "--clips", "--clip-frames", "8", "--clip-size", "160", "120"]):
        r = runner.invoke(main, args)
        assert r.exit_code == 0, (args, r.output, r.exception)
    clips = sorted((cap / "derived" / "mode_clips").glob("*.mp4"))
    assert clips, "the report stage rendered no mode clip"
    videos += [tmp_path / "raw.mp4", tmp_path / "render" / "render.mp4", tmp_path / "view.mp4", clips[0]]
    if chromium() is None:
        pytest.skip("no chromium on PATH: the browser check needs one")
    seen = video_durations(videos, tmp_path)
    for path in videos:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p", path
            expected = count_frames(path) / float(stream.average_rate)
            size = [stream.width, stream.height]
        assert isinstance(seen[path.name], list), (path, seen[path.name])
        assert seen[path.name][1:] == size and seen[path.name][0] == pytest.approx(expected, rel=0.05), (path, seen)
