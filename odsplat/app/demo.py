"""`odsplat demo` (what `make demo` runs): the toolkit end to end on the simulated rig, a guided 27-view capture with
faults that QC catches, the pipeline, a magnified orbit render and the report, and then the real LADISK recordings
imported and analysed when their folder exists.

An application over the stages, like the batch: it uses the stages' packages (their `__init__`) and the pipeline's
entries only. It never deletes a folder it did not make: each capture it makes carries a marker file (`MARKER`),
and a rerun redoes only a capture that has one.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import time
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path
from typing import Any

import tomli_w

from odsplat.acquisition import (
    CaptureSession,
    HammerTrigger,
    PlanSettings,
    QCLimits,
    SessionSettings,
    SimRigSettings,
    TextFeedback,
    choose_hammer,
    open_bench,
)
from odsplat.analysis import read_analysis
from odsplat.app.config import load_config
from odsplat.app.pipeline import run as run_pipeline
from odsplat.app.pipeline import run_stage
from odsplat.reconstruction import DynamicScene, camera_path, parse_times, render_sequence
from odsplat.spine.errors import InputError
from odsplat.spine.importer import import_capture
from odsplat.spine.shared_data import SHARED_DATA_ENV
from odsplat.spine.store import Capture

log = logging.getLogger(__name__)

SIM_NAME = "sim-rig"           # OUT/sim-rig: the simulated capture
BEAM_NAME = "ladisk-beam"      # OUT/ladisk-beam: the real recordings, imported
MARKER = ".odsplat-demo"       # in each capture the demo made: what allows a rerun to replace it
DEFAULT_SHARED_DATA = Path("..") / "shared" / "data"   # from the working directory: the repo's neighbour for make
FAULTS = "3:double_hit,9:dropped_packet"                # a rebound (the automatic hammer's double hit), lost samples


@dataclass(frozen=True)
class DemoScale:
    """How big the simulated part is: the capture, the settings laid over examples/demo.toml, the render."""

    name: str
    n_views: int
    n_frames: int                  # per take at 2000 fps
    pretrigger_frames: int
    faults: str                    # take numbers of this run: hil_sim's `parse_faults`
    settings: Mapping[str, Any]    # over odsplat/examples/demo.toml
    orbit: str                     # `odsplat render --camera`
    n_render: int                  # render times, evenly over the trained window (`odsplat render --times A:B:N`)
    alpha: float = 30.0            # the render's magnification in 3D


# 256 frames: 128 ms at 2000 fps, three cycles of the rig's lowest mode (23.5 Hz), for the sync and the image poles;
# the reconstruction trains on the first 64 timesteps after the impact (demo.toml). From a fresh clone, installation
# included, 7.5 min on two idle cores with magnify on three views (demo.toml); 15.5-17 min on two shared cores with
# all 27 magnified, and 300 frames did not fit 15 min there: the capture, sync and magnify grow with the frames.
FULL = DemoScale("full", n_views=27, n_frames=256, pretrigger_frames=10, faults=FAULTS, settings={},
                 orbit="orbit:16:30", n_render=16)
# The same steps at a size the test suite can afford (43 s on two idle cores): fewer views and
# frames, a coarser and shorter reconstruction, no 2D videos.
QUICK = DemoScale("quick", n_views=8, n_frames=40, pretrigger_frames=8, faults="3:double_hit,5:dropped_packet",
                  settings={"magnify": {"video": False},
                            "reconstruct": {"width_px": 64, "n_timesteps": 24, "fit": {"iters_t0": 150}}},
                  orbit="orbit:6:30", n_render=6)

# What `odsplat capture --sim --auto` records besides the plan and the frames: its options' defaults (a test holds
# the two together).
CAPTURE_DEFAULTS: dict[str, Any] = {"record_s": 0.5, "pretrigger_s": 0.02, "trigger_n": 10.0, "size": (400, 300),
                                    "bit_depth": 12, "seed": 0, "structure": "arm", "texture": "speckle",
                                    "floor_tag_m": 0.12, "min_tags": 2, "max_attempts": 5}


# ------------------------------------------------------------------------------------------ the result

@dataclass(frozen=True)
class ModeLine:
    """One mode of a capture's analysis, with the video's MAC where there is a video side."""

    freq_hz: float
    damping: float                 # ratio
    mac: float | None = None
    below_noise_floor: bool = False
    status: str | None = None      # under the MAC target (analysis.verdict.ModeStatus), where it was judged
    confused_with: tuple[int, ...] = ()   # the modes the sensors cannot tell it from


@dataclass
class CaptureSummary:
    """One capture of the demo: its modes and where its files are."""

    name: str
    root: Path
    what: str                      # a few words on where it comes from
    modes: list[ModeLine]
    video: bool                    # the analysis has a video side (MAC columns)
    verdict: str | None            # the analysis's MAC verdict line
    report: Path
    render: Path | None = None

    def lines(self) -> list[str]:
        out = [f"{self.name} ({self.what}):"]
        head = "  mode  frequency (Hz)  damping (%)"
        out.append(head + ("  MAC video/accelerometers" if self.video else ""))
        for k, m in enumerate(self.modes):
            line = f"  {k + 1:>4}  {m.freq_hz:>14.2f}  {100 * m.damping:>11.2f}"
            if self.video:
                line += "  " + ("-" if m.mac is None else f"{m.mac:.3f}"
                                + (" (below the video's noise floor)" if m.below_noise_floor else ""))
                if m.status is not None and not m.below_noise_floor:
                    line += f"  {m.status}" + (f" (alike at the sensors: mode{'s' if len(m.confused_with) > 1 else ''} "
                                               f"{', '.join(str(j) for j in m.confused_with)})"
                                               if m.confused_with and m.status != "met" else "")
            out.append(line)
        if self.verdict:
            out.append(f"  verdict: {self.verdict}")
        out.append(f"  report: {self.report}")
        if self.render is not None:
            out.append(f"  render: {self.render}")
        return out


@dataclass
class DemoResult:
    out: Path
    scale: str
    captures: list[CaptureSummary] = field(default_factory=list)
    skipped: str | None = None     # why the real recordings were not analysed
    seconds: float = 0.0
    steps: list[tuple[str, float]] = field(default_factory=list)   # (step, seconds)

    def text(self) -> str:
        """The summary printed at the end: each capture's modes and MAC, the reports, the viewer command."""
        lines = [f"odsplat demo ({self.scale}) done in {self.seconds:.0f} s ("
                 + ", ".join(f"{name} {sec:.0f} s" for name, sec in self.steps) + f"); captures in {self.out}"]
        for c in self.captures:
            lines += c.lines()
        if self.skipped:
            lines.append(f"{BEAM_NAME}: skipped: {self.skipped}")
        sim = next((c for c in self.captures if c.name == SIM_NAME), None)
        if sim is not None:
            lines.append(f"view it in 3D: odsplat view {sim.root}")
        return "\n".join(lines)


def summarize(capture: Capture, what: str, render: Path | None = None) -> CaptureSummary:
    """A capture's modes from its analysis.json, each with the video's MAC as the report's summary pairs them."""

    doc = read_analysis(capture)
    pairs = doc.pair_by_mode()
    v = doc.correlation.verdict if doc.correlation is not None else None
    statuses = {s.mode: s for s in v.modes} if v is not None else {}
    modes = [ModeLine(m.freq_hz, m.damping, pairs[k].mac if k in pairs else None,
                      k in pairs and bool(pairs[k].below_noise_floor),
                      statuses[k + 1].status if k + 1 in statuses else None,
                      statuses[k + 1].confused_with if k + 1 in statuses else ()) for k, m in enumerate(doc.modes)]
    verdict = v.line if v is not None else None
    return CaptureSummary(capture.root.name, capture.root, what, modes, doc.video is not None, verdict,
                          capture.paths.report_html, render)


# ------------------------------------------------------------------------------------------ inputs

def shared_data_folder(given: Path | None) -> tuple[Path | None, str | None]:
    """The folder of real recordings, or None and why not. Given (--shared-data) or named by $ODSPLAT_SHARED_DATA,
    it must exist; otherwise ../shared/data from the working directory is used when it exists."""
    where = "--shared-data"
    if given is None and os.environ.get(SHARED_DATA_ENV):
        given, where = Path(os.environ[SHARED_DATA_ENV]), f"${SHARED_DATA_ENV}"
    if given is not None:
        if not given.is_dir():
            raise InputError(given, f"no such folder ({where} names the folder of real recordings)")
        return given, None
    if DEFAULT_SHARED_DATA.is_dir():
        return DEFAULT_SHARED_DATA, None
    return None, (f"{DEFAULT_SHARED_DATA} not found; give the folder of real recordings with --shared-data DIR "
                  f"(make demo SHARED_DATA=DIR) or ${SHARED_DATA_ENV}")


def _check_replaceable(path: Path) -> None:
    """The demo may replace `path` only if it made it (its marker is there) or it is an empty folder."""
    if not (path.exists() or path.is_symlink()):
        return
    if path.is_dir() and not path.is_symlink() and ((path / MARKER).is_file() or not any(path.iterdir())):
        return
    raise InputError(path, f"exists and is not a capture odsplat demo made (no {MARKER} in it); move it away or "
                           "choose another OUT")


def check_out(out: Path, with_beam: bool) -> None:
    """Refuse, before any work, an OUT that is a file or captures the demo would replace but did not make."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "is not a folder; OUT is the folder the demo writes its captures into")
    _check_replaceable(out / SIM_NAME)
    if with_beam:
        _check_replaceable(out / BEAM_NAME)


def _mark(root: Path, scale: str) -> None:
    doc = {"made_by": "odsplat demo", "scale": scale, "created_utc": datetime.now(timezone.utc).isoformat()}
    (root / MARKER).write_text(json.dumps(doc) + "\n")


def _replace(path: Path) -> None:
    _check_replaceable(path)
    if path.exists():
        shutil.rmtree(path)


def example(name: str) -> str:
    """The text of a file shipped in odsplat/examples/ (the demo's settings, the LADISK rig file)."""
    return resources.files("odsplat").joinpath("examples", name).read_text(encoding="utf-8")


def _merged(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out.get(k, {}), v) if isinstance(v, Mapping) else v
    return out


def demo_settings(scale: DemoScale) -> str:
    """The simulated capture's odsplat.toml: examples/demo.toml, with the scale's settings laid over."""
    text = example("demo.toml")
    if not scale.settings:
        return text
    merged = _merged(tomllib.loads(text), scale.settings)
    return (f"# odsplat/examples/demo.toml at the demo's {scale.name} scale (odsplat/app/demo.py)\n\n"
            + tomli_w.dumps(merged))


# ------------------------------------------------------------------------------------------ the steps

def simulated_capture(root: Path, scale: DemoScale, echo: Callable[[str], None], seed: int | None = None) -> None:
    """The guided capture of `odsplat capture --sim --auto` (its defaults, `CAPTURE_DEFAULTS`) with the scale's
    views, frames and faults; each take's verdict through `echo`. The set-up is opened as the command opens it
    (acquisition.open_bench). seed: the rig's and the camera's noise, the hammer's scatter (None: the capture's
    default, 0)."""

    d = dict(CAPTURE_DEFAULTS, **({} if seed is None else {"seed": seed}))

    class TakeLines(TextFeedback):
        """Each take's verdict; the instructions for placing the camera are for a person."""

        def show_view(self, view: Any, n_views: int, instructions: str) -> None:
            pass

    rig = SimRigSettings(size_px=d["size"], bit_depth=d["bit_depth"], seed=d["seed"], structure=d["structure"],
                         texture=d["texture"], floor_tag_m=d["floor_tag_m"], faults=scale.faults)
    hammer = choose_hammer(None, simulated_engineer=True, lab_settings=None, has_lab=False)
    session = SessionSettings(name=root.name, plan=PlanSettings(n_views=scale.n_views), n_frames=scale.n_frames,
                              pretrigger_frames=scale.pretrigger_frames, max_attempts=d["max_attempts"],
                              trigger=HammerTrigger(pretrigger_s=d["pretrigger_s"], record_s=d["record_s"]),
                              hammer=hammer, limits=QCLimits(min_tags=d["min_tags"]),
                              hit_timeout_s=10.0)  # the rig's hammer strikes within ms: only a hit lost on the
                                                   # link waits, and not a minute
    with open_bench(sim=rig, hammer=hammer is not None) as bench:
        report = CaptureSession(root, session, bench, feedback=TakeLines(echo)).run()
    echo(report.summary())
    if not report.complete:
        log.warning("%s: the capture is incomplete (%s); the pipeline goes on with the views it has", root,
                    report.summary())


def render_orbit(capture: Capture, scale: DemoScale) -> Path:
    """`odsplat render --camera ORBIT --times A:B:N --alpha 30` over the trained window A..B; the mp4."""

    scene = DynamicScene.load(capture)
    times = parse_times(f"{float(scene.times_s[0])!r}:{float(scene.times_s[-1])!r}:{scale.n_render}", scene.times_s)
    cameras = camera_path(capture, scale.orbit, len(times), None)
    paths = render_sequence(scene, cameras, times, capture.paths.render_dir, alpha=scale.alpha, fps=30.0, mp4=True)
    return paths[-1]


def run_demo(out: Path, *, quick: bool = False, shared_data: Path | None = None,
             echo: Callable[[str], None] | None = None, seed: int | None = None) -> DemoResult:
    """Run the demo into `out`: OUT/sim-rig (made anew each time) and, when the real recordings are found
    (`shared_data_folder`), OUT/ladisk-beam. `echo` gets a line per step and per stage. seed: the simulated
    capture's (`simulated_capture`): the same demo on another draw of its noise."""
    say = echo or (lambda line: log.info("%s", line))
    scale = QUICK if quick else FULL
    started = time.perf_counter()
    data, skipped = shared_data_folder(shared_data)
    check_out(out, with_beam=data is not None)
    out.mkdir(parents=True, exist_ok=True)
    result = DemoResult(out, scale.name, skipped=skipped)
    n_steps = 5
    clock = [time.perf_counter()]

    def step(k: int, name: str, line: str) -> None:
        now = time.perf_counter()
        if result.steps:
            result.steps[-1] = (result.steps[-1][0], now - clock[0])
        clock[0] = now
        result.steps.append((name, 0.0))
        say(f"[demo {k}/{n_steps}] {line}")

    sim_root = out / SIM_NAME
    step(1, "capture", f"a guided {scale.n_views}-view capture on the simulated rig into {sim_root} "
                       f"({scale.n_frames} frames per take at 2000 fps; faults injected: {scale.faults})")
    _replace(sim_root)
    sim_root.mkdir()
    _mark(sim_root, scale.name)
    simulated_capture(sim_root, scale, say, seed)

    step(2, "pipeline", f"the pipeline on {sim_root} (its odsplat.toml: odsplat/examples/demo.toml"
                        + (", quick scale)" if scale.settings else ")"))
    (sim_root / "odsplat.toml").write_text(demo_settings(scale), encoding="utf-8")
    cap = Capture.open(sim_root)
    config = load_config(cap)
    done = run_pipeline(cap, config, echo=say, stop="analyze")     # the report once, after the render (step 4)
    say(done.text())

    step(3, "render", f"an orbit render magnified {scale.alpha:g}x in 3D ({scale.orbit}, {scale.n_render} times over "
                      "the reconstruction's window)")
    render = render_orbit(cap, scale)
    say(f"render -> {render}")

    step(4, "report", "the report, with the render and each mode's amplified clip (derived/mode_clips/)")
    run_stage(cap, "report", config)
    result.captures.append(summarize(cap, f"simulated rig, {scale.n_views} views x {scale.n_frames} frames",
                                     render))

    if data is None:
        step(5, "real recordings", f"the real LADISK recordings: skipped: {skipped}")
    else:
        beam_root = out / BEAM_NAME
        step(5, "real recordings", f"the real LADISK beam recordings from {data} into {beam_root}")
        _replace(beam_root)

        rig = resources.files("odsplat").joinpath("examples", "ladisk-beam.toml")
        with resources.as_file(rig) as rig_path:
            beam = import_capture(rig_path, beam_root, data_dir=data)
        _mark(beam_root, scale.name)
        say(f"imported {len(beam.manifest.takes)} takes")
        done = run_pipeline(beam, load_config(beam), echo=say)
        say(done.text())
        result.captures.append(summarize(beam, "real recordings: LADISK free-free steel beam"))
    end = time.perf_counter()
    result.steps[-1] = (result.steps[-1][0], end - clock[0])
    result.seconds = end - started
    log.info("demo done in %.1f s", result.seconds)
    return result


__all__ = ["BEAM_NAME", "FULL", "MARKER", "QUICK", "SIM_NAME", "CaptureSummary", "DemoResult", "DemoScale",
           "ModeLine", "check_out", "demo_settings", "run_demo", "shared_data_folder", "summarize"]
