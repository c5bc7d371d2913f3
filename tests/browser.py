"""A page as a reader sees it: the order of a report's sections in its HTML, and what headless Chromium shows of it
in a first screen (where chosen elements end, how many 3D plots it drew, the errors it met, the requests it made
beyond the file itself). Chromium is found on PATH; callers skip without it."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

SCREEN = (1400, 900)


def chromium() -> str | None:
    return next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)


def page_title(page: Path, folder: Path, *flags: str, budget_ms: int = 8000,
               timeout_s: float = 120) -> tuple[str | None, subprocess.CompletedProcess]:
    """The title headless Chromium leaves on `page` once its virtual time (`budget_ms`) has run, with `flags` beside
    the usual ones and its profile in `folder` (None where it dumped no page), and the run itself."""
    cmd = [chromium(), "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", *flags,
           f"--user-data-dir={folder / 'profile'}", f"--virtual-time-budget={budget_ms}", "--dump-dom", page.as_uri()]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"headless Chromium did not finish in {timeout_s:g} s")
    title = re.search(r"<title>(.*?)</title>", run.stdout, re.S)
    return (None if title is None else title.group(1).replace("&quot;", '"').replace("&amp;", "&")), run


def section_order(html: str) -> list[str]:
    """The ids of the page's top-level sections, in the order they come."""
    return re.findall(r'<section id="([a-z0-9-]+)"', html)


_PROBE = """<script>
window.addEventListener("load", () => setTimeout(() => {{
  const bottom = {{}};
  for (const id of {ids}) {{
    const e = document.getElementById(id);
    bottom[id] = e ? Math.round(e.getBoundingClientRect().bottom) : -1;
  }}
  document.title = "PROBE " + JSON.stringify({{
    bottom, drawn: Number(document.body.dataset.shapes3d || 0),
    errors: document.body.dataset.shapes3dErrors || "",
    canvases: document.querySelectorAll(".shape3d canvas").length,
    requests: performance.getEntriesByType("resource").map((e) => e.name) }});
}}, 2500));
</script>"""


def first_screen(page: Path, folder: Path, ids: tuple[str, ...], size: tuple[int, int] = SCREEN) -> dict:
    """`page` opened in headless Chromium at `size`: {"bottom": {id: px from the top, -1 where absent}, "drawn":
    3D plots drawn, "errors": the page's script errors, "canvases", "requests": every URL the page asked for
    beyond inline data (its resource timing entries; no name resolves, so nothing would leave), "console": every
    line the page logged to its console}."""
    probe = folder / "probe.html"
    html = page.read_text()
    probe.write_text(html.replace("</body>", _PROBE.format(ids=json.dumps(list(ids))) + "</body>"))
    title, run = page_title(probe, folder, "--enable-unsafe-swiftshader", "--enable-logging=stderr",
                            "--host-resolver-rules=MAP * ~NOTFOUND", f"--window-size={size[0]},{size[1]}")
    if title is None or not title.startswith("PROBE "):
        pytest.fail(f"the page said nothing (exit {run.returncode}): {run.stderr[-1500:]}")
    out = json.loads(title[len("PROBE "):])
    out["requests"] = [u for u in out["requests"] if not u.startswith(("data:", "blob:"))]
    # what the page logged, less the browser's performance advice on reading pixels back (plotly's WebGL picking
    # does, and the software GL of a headless run says it stalls)
    advice = ("Canvas2D: Multiple readback", "GL Driver Message (OpenGL, Performance")
    out["console"] = [line for line in run.stderr.splitlines()
                      if ":CONSOLE" in line and not any(a in line for a in advice)]
    return out


_VIDEOS = """<!doctype html><html><head><title>WAITING</title></head><body>
{videos}
<script>
const result = {{}};
const all = document.querySelectorAll("video");
const done = () => {{
  if (Object.keys(result).length === all.length) document.title = "VIDEOS " + JSON.stringify(result);
}};
all.forEach((v) => {{
  v.addEventListener("error", () => {{ result[v.dataset.name] = "ERROR " + (v.error ? v.error.code : "?"); done(); }});
  v.addEventListener("loadedmetadata", () => {{
    result[v.dataset.name] = [v.duration, v.videoWidth, v.videoHeight]; done();
  }});
}});
</script></body></html>
"""


def video_durations(videos: list[Path], folder: Path) -> dict:
    """Each mp4 loaded into a <video> of one page in headless Chromium: {file name: [duration s, width, height]}, or
    "ERROR code" where it refuses one (MediaError 4: no stream it can play)."""
    tags = "\n".join(f'<video muted preload="metadata" data-name="{p.name}" src="{p.resolve().as_uri()}"></video>'
                     for p in videos)
    page = folder / "videos.html"
    page.write_text(_VIDEOS.format(videos=tags))
    title, run = page_title(page, folder, "--allow-file-access-from-files", budget_ms=15000)
    if title is None or not title.startswith("VIDEOS "):
        pytest.fail(f"the page said nothing of the videos (exit {run.returncode}): {run.stderr[-1500:]}")
    return json.loads(title[len("VIDEOS "):])
