"""Each mode's amplified clip on the 3D path (issue 46): the report stage renders one per mode the analysis has a
video shape of, from the Gaussians (`odsplat.app.report`), the structure moving in it; the report plays each inline
in that mode's section; turned off, no clip is left behind; a link planted where the clips go is refused."""
from __future__ import annotations

import os
import re

import av
import numpy as np
from click.testing import CliRunner

from odsplat.analysis import read_results_h5
from odsplat.app.cli import main
from odsplat.spine.store import Capture

from .conftest import piped_copy


def _frames(path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def _modes_section(html: str) -> str:
    return html[html.index('<section id="modes">'):html.index("</section>", html.index('<section id="modes">'))]


def test_each_mode_with_a_video_shape_gets_a_moving_clip_that_the_report_plays(piped_original, tmp_path):
    cap = piped_copy(piped_original, tmp_path / "c" / "cap")
    r = CliRunner().invoke(main, ["report", str(cap), "--clips", "--clip-frames", "8", "--clip-size", "160", "120"])
    assert r.exit_code == 0, (r.output, r.exception)
    capture = Capture.open(cap)
    results = read_results_h5(capture.paths.analysis_dir / "results.h5")
    shaped = sorted(int(m.group(1)) for s in results.shapes if (m := re.fullmatch(r"video mode (\d+)", s.name)))
    assert shaped, "the piped capture's analysis has no video shape"
    clips = sorted(capture.paths.mode_clips_dir.glob("*.mp4"))
    assert [p.name for p in clips] == [f"mode_{k:02d}.mp4" for k in shaped]
    for path in clips:
        frames = _frames(path)
        assert len(frames) == 8 and frames[0].shape == (120, 160, 3), path
        # the structure moves through the cycle: the clip starts furthest from rest, and half a cycle on it stands
        # as far on the other side, so those two frames differ most, in many pixels by far more than the encoder's
        # noise; a quarter cycle on, it passes its rest and differs from both by about half as much
        moved = [int((np.abs(frames[0].astype(int) - f).max(axis=2) > 40).sum()) for f in frames]
        assert moved[4] >= 20 and moved[4] == max(moved), (path, moved)
    section = _modes_section((cap / "derived" / "analysis" / "report.html").read_text())
    for k in shaped:
        block = section[section.index(f'id="mode-{k}"'):]
        block = block[:block.index('<div class="mode', 1)] if '<div class="mode' in block[1:] else block
        assert '<video src="data:video/mp4;base64,' in block, k
    assert section.count("data:video/mp4") == len(shaped)

    # turned off: the clips go, and the page shows none
    r = CliRunner().invoke(main, ["report", str(cap), "--no-clips"])
    assert r.exit_code == 0, (r.output, r.exception)
    assert not list(capture.paths.mode_clips_dir.glob("*.mp4"))
    assert "data:video/mp4" not in _modes_section((cap / "derived" / "analysis" / "report.html").read_text())


def test_a_link_where_the_clips_go_is_refused_and_nothing_is_deleted_through_it(piped_original, tmp_path):
    cap = piped_copy(piped_original, tmp_path / "c" / "cap")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mode_01.mp4").write_bytes(b"not ours")
    os.symlink(elsewhere, cap / "derived" / "mode_clips")
    r = CliRunner().invoke(main, ["report", str(cap), "--no-clips"])
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert "mode_clips" in r.output and "link" in r.output, r.output
    assert (elsewhere / "mode_01.mp4").read_bytes() == b"not ours"


def test_a_reconstruction_the_viewer_cannot_read_leaves_the_page_without_clips(piped_original, tmp_path, caplog):
    """The clips are the page's extra: a damaged trajectories.npz (cut short after the analysis ran) leaves the
    report written without them, and a warning naming the file."""
    cap = piped_copy(piped_original, tmp_path / "c" / "cap")
    npz = cap / "derived" / "reconstruction" / "trajectories.npz"
    npz.write_bytes(npz.read_bytes()[:1000])
    r = CliRunner().invoke(main, ["report", str(cap), "--clips"])
    assert r.exit_code == 0, (r.output, r.exception)
    assert "no mode clips" in caplog.text and "trajectories.npz" in caplog.text, caplog.text
    assert not list((cap / "derived" / "mode_clips").glob("*.mp4"))
    assert "data:video/mp4" not in _modes_section((cap / "derived" / "analysis" / "report.html").read_text())
