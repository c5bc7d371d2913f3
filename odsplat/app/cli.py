"""The `odsplat` command line: `odsplat run` for the whole pipeline, and one thin subcommand per stage calling the
same entry; errors are one line naming the culprit."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from odsplat.app.config import STAGES, load_config
from odsplat.spine.checks import MAX_MAGNIFICATION, PLAYBACK_FPS, WIDTH_PX, WORKERS, Range, check_number, maybe
from odsplat.spine.errors import OdsplatError, exit_if_hdf5_unclosed, storage_error


class _Group(click.Group):
    """Turns odsplat's own errors into one line on stderr and exit status 2, with no traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except OdsplatError as exc:
            line, storage = str(exc), storage_error(exc)
        except Exception as exc:   # a full disk, a read-only folder: one line too; anything else is a bug
            storage = storage_error(exc)
            if storage is None:
                raise
            line = str(storage)
        click.echo(f"odsplat: error: {line}", err=True)
        if storage is not None:
            exit_if_hdf5_unclosed()
        sys.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
@click.version_option(package_name="odsplat")
def main(verbose: int) -> None:
    """odsplat: motion-magnified 3D operational deflection shapes from impact tests."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def _given(**fields: Any) -> dict[str, Any]:
    """The settings the user gave on the command line, as a table for the stage: FIELD=VALUE for each option given
    (not defaulted). FIELD is a name, a dotted name for a nested one (fit.iters_t0), or a tuple of them, or
    (FIELD, convert) with a function of the option's value."""
    ctx = click.get_current_context()
    table: dict[str, Any] = {}
    for param, target in fields.items():
        if ctx.get_parameter_source(param) not in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT):
            continue
        names, convert = (target[0], target[1]) if callable(target[-1]) else (target, None)
        value = ctx.params[param]
        value = convert(value) if convert else value
        for name in (names,) if isinstance(names, str) else names:
            *path, last = name.split(".")
            node = table
            for part in path:
                node = node.setdefault(part, {})
            node[last] = list(value) if isinstance(value, tuple) else value
    return table


def _set_wait(ctx: click.Context, _param: click.Parameter, value: bool) -> None:
    ctx.meta["odsplat.wait"] = value


def _set_derived(ctx: click.Context, _param: click.Parameter, value: Path | None) -> None:
    ctx.meta["odsplat.derived"] = value


def _wait_option(command):
    """--wait and --derived, for the commands that write a capture's derived files."""
    command = click.option(
        "--derived", type=click.Path(path_type=Path, file_okay=False), default=None, expose_value=False,
        callback=_set_derived, is_eager=True,
        help="Read and write the derived files in this folder instead of the capture's derived/ (a read-only "
             "capture, a faster disk).")(command)
    return click.option(
        "--wait", is_flag=True, expose_value=False, callback=_set_wait,
        help="When another odsplat command is writing this capture, wait for it to finish instead of stopping.",
    )(command)


def _waits() -> bool:
    return bool(click.get_current_context().meta.get("odsplat.wait"))


def _open(capture_dir: Path):
    """The capture, with its derived files where --derived says."""
    from odsplat.spine.store import Capture

    return Capture.open(capture_dir, derived=click.get_current_context().meta.get("odsplat.derived"))


def _locked(capture: Any):
    """The capture's lock for a command that writes it outside the pipeline (recover, geometry, render)."""
    from odsplat.spine.lock import capture_lock

    return capture_lock(capture, wait=_waits())


def _stage(capture_dir: Path, stage: str, given: dict[str, Any]) -> tuple[Any, Any]:
    """Run one stage through the pipeline's entry: the capture's configuration with the options given laid over.
    Returns (capture, the stage's result)."""
    from odsplat.app.pipeline import run_stage

    cap = _open(capture_dir)
    config = load_config(cap)
    if given:
        config = config.updated({stage: given}, "the command line")
    return cap, run_stage(cap, stage, config, wait=_waits()).result


@main.command()
@click.argument("capture", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def info(capture: Path, as_json: bool) -> None:
    """Summarise a capture: takes, frames, channels, sizes and QC flags."""
    from odsplat.spine.summary import summarize

    summary = summarize(capture)
    click.echo(json.dumps(summary.to_dict(), indent=2) if as_json else summary.to_text())


@main.command("import")
@click.argument("rig", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="New capture directory.")
@click.option("--data", type=click.Path(path_type=Path), default=None,
              help="Folder the rig's file names are relative to (default: the rig file's folder).")
def import_(rig: Path, out: Path, data: Path | None) -> None:
    """Build a capture from recordings of other equipment described by a RIG file (TOML, see docs/import.md)."""
    from odsplat.spine.importer import import_capture

    capture = import_capture(rig, out, data_dir=data)
    click.echo(f"imported {len(capture.manifest.takes)} takes into {capture.root}")


@main.command()
@_wait_option
@click.argument("capture", type=click.Path(path_type=Path))
def recover(capture: Path) -> None:
    """Recover takes left unfinished by a crash, keeping every flushed frame and sample."""
    from odsplat.spine.integrity import listed_take_problems

    cap = _open(capture)
    with _locked(cap):
        reports = cap.recover()
    lost = listed_take_problems(cap)
    if not reports and not lost:
        click.echo("nothing to recover: every listed take's file is there and whole, and no take is unfinished")
    for r in reports:
        click.echo(f"{r.name}: {'recovered' if r.recovered else 'NOT recovered'}: {r.message}")
    for check in lost:
        click.echo(f"{check.name}: NOT recoverable here: {check.status}: {'; '.join(check.details)} (a raw take is "
                   "written once: restore the file from a copy; `odsplat verify` checks the others)")
    if any(not r.recovered for r in reports) or lost:
        sys.exit(1)


@main.command()
@click.argument("capture", type=click.Path(path_type=Path))
def verify(capture: Path) -> None:
    """Read every take of CAPTURE whole through its checksums: each take OK, damaged (which frames or samples),
    missing, truncated, unfinished, not listed, or without checksums (an older take: readable, but damage cannot be
    detected). Exit 1 when anything is wrong."""
    from odsplat.spine.integrity import verify_capture

    cap = _open(capture)
    checks = verify_capture(cap)
    for check in checks:
        click.echo(check.line())
    bad = [c for c in checks if not c.ok]
    unchecked = [c for c in checks if c.status == "no checksums"]
    click.echo(f"{len(checks)} take(s): {len(checks) - len(bad)} whole"
               + (f" ({len(unchecked)} without checksums)" if unchecked else "")
               + (f", {len(bad)} with problems" if bad else ""))
    if bad:
        sys.exit(1)


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.argument("geometry_file", type=click.Path(path_type=Path), required=False)
def geometry(capture_dir: Path, geometry_file: Path | None) -> None:
    """Place the sensors after the recording: with GEOMETRY_FILE (TOML [[sensors]] tables: name, position_m,
    direction), set their positions and directions in the capture; without it, print the capture's geometry in
    that format, to edit. The raw takes are untouched; `odsplat run` then redoes the analysis."""
    from odsplat.spine.sensors import apply_geometry, geometry_toml, read_geometry

    cap = _open(capture_dir)
    if geometry_file is None:
        click.echo(geometry_toml(cap), nl=False)
        return
    with _locked(cap):
        changes = apply_geometry(cap, read_geometry(geometry_file), geometry_file)
    click.echo("\n".join(changes) if changes else "the geometry is as the file says already")


def _span_options(command):
    """--from, --to and --force: which stages `odsplat run` and `odsplat batch` run."""
    for option in reversed((
            click.option("--from", "start", type=click.Choice(STAGES), default=None,
                         help="Run from this stage on, whether or not it is current."),
            click.option("--to", "stop", type=click.Choice(STAGES), default=None, help="Stop after this stage."),
            click.option("--force", "force", type=click.Choice(STAGES), multiple=True,
                         help="Run this stage even if it is current (repeatable); what depends on it follows."))):
        command = option(command)
    return command


@main.command("run")
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@_span_options
@click.option("--config", "config_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Configuration file (default: CAPTURE_DIR/odsplat.toml when it exists).")
@click.option("--set", "sets", multiple=True, metavar="STAGE.FIELD=VALUE",
              help="Override one setting, e.g. magnify.alpha=30 (repeatable; VALUE in TOML syntax).")
def run_(capture_dir: Path, start: str | None, stop: str | None, force: tuple[str, ...], config_path: Path | None,
         sets: tuple[str, ...]) -> None:
    """Run the pipeline on CAPTURE_DIR, from the raw takes to the report; stages whose outputs are current are
    skipped, stale ones rerun with everything downstream (docs/config.md)."""
    from odsplat.app.pipeline import run

    cap = _open(capture_dir)
    config = load_config(cap, path=config_path, sets=sets)
    result = run(cap, config, start=start, stop=stop, force=force, echo=click.echo, wait=_waits())
    click.echo(result.text())


@main.command("batch")
@click.argument("captures", nargs=-1, required=True, type=click.Path(path_type=Path, file_okay=False, exists=True))
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="A running Dask scheduler (e.g. tcp://host:8786) whose workers see the captures at these paths; "
                   "default: a local cluster.")
@click.option("--workers", type=int, default=None,
              help="Worker processes of the local cluster, one thread each (default: one per core).")
@_span_options
@click.option("--config", "config_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Configuration file for every capture (default: each capture's odsplat.toml when it exists).")
@click.option("--set", "sets", multiple=True, metavar="STAGE.FIELD=VALUE",
              help="Override one setting in every capture (repeatable; VALUE in TOML syntax).")
def batch_(captures: tuple[Path, ...], scheduler: str | None, workers: int | None, start: str | None,
           stop: str | None, force: tuple[str, ...], config_path: Path | None, sets: tuple[str, ...]) -> None:
    """Run the pipeline on many CAPTURES at once on Dask distributed: a task per capture, and the views of the
    per-view stages (sync's aligned frames, magnify) as tasks of their own. Stages that are current are skipped
    as by `odsplat run`; a capture that fails is reported with its stage and the others finish (exit status 1).
    Prints the Dask dashboard's address, and a line per capture and stage as they finish."""
    from odsplat.app.batch import run_batch

    check_number("--workers", workers, maybe(WORKERS))
    # Dask's own INFO lines (workers started and closed) only with -v, like odsplat's
    logging.getLogger("distributed").setLevel(max(logging.WARNING, logging.getLogger().level))
    result = run_batch(captures, scheduler=scheduler, workers=workers, start=start, stop=stop, force=force,
                       sets=sets, config_path=config_path, echo=click.echo)
    click.echo(result.text())
    if result.failed:
        sys.exit(1)


@main.command("config")
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--config", "config_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Configuration file (default: CAPTURE_DIR/odsplat.toml when it exists).")
@click.option("--set", "sets", multiple=True, metavar="STAGE.FIELD=VALUE", help="Override one setting (repeatable).")
@click.option("--status", is_flag=True, help="Also say which stages are current.")
def config_(capture_dir: Path, config_path: Path | None, sets: tuple[str, ...], status: bool) -> None:
    """Print the effective configuration of CAPTURE_DIR (defaults, its odsplat.toml, --set) as TOML."""

    cap = _open(capture_dir)
    config = load_config(cap, path=config_path, sets=sets)
    click.echo(config.to_toml(), nl=False)
    if status:
        from odsplat.app.pipeline import status as stage_status

        click.echo("")
        for name, current, why in stage_status(cap, config):
            state = "n/a" if why.startswith("does not apply") else "current" if current else "stale"
            click.echo(f"# {name:<12} {state}: {why}")


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--force-band", "force_band_n", type=(float, float), default=None,
              help="Planned peak force (N); takes outside are rejected (default: any).")
def qc(capture_dir: Path, force_band_n: tuple[float, float] | None) -> None:
    """Check every take's hit from its file (impacts, force band, lost samples, dropped frames): derived/qc.json."""
    _, result = _stage(capture_dir, "qc", _given(force_band_n="force_band_n"))
    click.echo(result.summary())


@main.command()
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--sim", is_flag=True, help="Capture from the simulated rig (hil_sim) instead of the lab's devices.")
@click.option("--auto", is_flag=True, help="With --sim: the simulated engineer places, hits and accepts; no questions.")
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None,
              help="Lab configuration (TOML: DAQ port and channels, camera, tags); see acquisition/lab.py.")
@click.option("--views", type=int, default=27, show_default=True, help="Number of planned views.")
@click.option("--radius-m", type=float, default=1.6, show_default=True, help="Camera distance from the target.")
@click.option("--elevation-deg", type=(float, float), default=(15.0, 60.0), show_default=True,
              help="Elevation band of the views.")
@click.option("--target-m", type=(float, float, float), default=(0.2, 0.0, 0.3), show_default=True,
              help="Point the cameras aim at (world, m).")
@click.option("--frames", "n_frames", type=int, default=100, show_default=True, help="Frames per take.")
@click.option("--pretrigger-frames", type=int, default=10, show_default=True, help="Frames kept before the trigger.")
@click.option("--fps", type=float, default=None, help="Camera frame rate (default: the camera's).")
@click.option("--record-s", type=float, default=0.5, show_default=True, help="DAQ record length per take.")
@click.option("--pretrigger-s", type=float, default=0.02, show_default=True, help="DAQ time kept before the trigger.")
@click.option("--trigger-n", type=float, default=10.0, show_default=True, help="Hammer force that triggers (N).")
@click.option("--force-band", type=(float, float), default=(20.0, 2000.0), show_default=True,
              help="Planned peak force (N); hits outside are redone.")
@click.option("--min-tags", type=int, default=2, show_default=True,
              help="Floor tags QC wants in view (0: none; sync and poses deal with views that show too few).")
@click.option("--static-photos", is_flag=True, help="Also take one still photo per view into OUT/static/.")
@click.option("--max-attempts", type=int, default=5, show_default=True, help="Takes per view before moving on.")
@click.option("--size", default="400x300", show_default=True, help="With --sim: image size WxH in px.")
@click.option("--hammer", type=click.Choice(["auto", "manual"]), default=None,
              help="Fire an automatic hammer on every take, or let the engineer hit. Default: auto with --sim --auto "
                   "or a [hammer] section in the lab file, else manual.")
@click.option("--hammer-force-n", type=float, default=None,
              help="Automatic hammer: the set force (N; default 200, or the lab file's). "
                   "Its band replaces --force-band.")
@click.option("--hammer-tolerance", type=float, default=None,
              help="Automatic hammer: QC accepts a peak within force * (1 +- this) (default 0.03).")
@click.option("--hammer-link", type=click.Choice(["serial", "can"]), default="serial", show_default=True,
              help="With --sim: the simulated automatic hammer's link.")
@click.option("--sim-faults", default="",
              help="With --sim: faults on takes of this run, e.g. '2:double_hit,5:disconnect' "
                   "(double_hit, overload, dropped_packet, disconnect, dropped_frames; with the automatic hammer also "
                   "rebound, hammer_not_ready, hammer_stuck, hammer_no_response).")
@click.option("--seed", type=int, default=0, show_default=True, help="With --sim: random seed of the rig and engineer.")
@click.option("--structure", default="arm", show_default=True, help="With --sim: the rig, 'arm' or 'plate'.")
@click.option("--texture", default="speckle", show_default=True,
              help="With --sim: the structure's texture, 'speckle', 'value_noise' or 'checker'.")
@click.option("--floor-tag-m", type=float, default=0.12, show_default=True,
              help="With --sim: the floor tags' size (m): 0.12 is ~20 px at 256x256.")
@click.option("--bit-depth", type=int, default=12, show_default=True,
              help="With --sim: 12 (in 16-bit words, as Photron writes them) or 8.")
@click.option("--window/--no-window", default=None, help="Live plots in a window (default: when a display exists).")
def capture(out: Path, sim: bool, auto: bool, config_path: Path | None, views: int, radius_m: float,
            elevation_deg: tuple[float, float], target_m: tuple[float, float, float], n_frames: int,
            pretrigger_frames: int, fps: float | None, record_s: float, pretrigger_s: float, trigger_n: float,
            force_band: tuple[float, float], min_tags: int, static_photos: bool, max_attempts: int, size: str,
            hammer: str | None,
            hammer_force_n: float | None, hammer_tolerance: float | None, hammer_link: str, sim_faults: str, seed: int,
            structure: str, texture: str, floor_tag_m: float, bit_depth: int, window: bool | None) -> None:
    """Guided multi-view capture into OUT: place the camera at each planned view, hit, QC, accept or redo.

    Stop at any time (even by a crash) and run the same command again to resume."""
    from odsplat.acquisition import (
        CaptureSession,
        HammerTrigger,
        LabBench,
        PlanSettings,
        PlotFeedback,
        QCLimits,
        SessionSettings,
        TextFeedback,
        choose_hammer,
        display_available,
        load_lab_config,
    )
    from odsplat.spine.errors import InputError

    if sim == (config_path is not None):
        raise InputError("odsplat capture", "give exactly one of --sim or --config LAB.toml")
    if auto and not sim:
        raise InputError("odsplat capture", "--auto needs --sim: in the lab a person places the camera and hits")
    lab = load_lab_config(config_path) if config_path is not None else None
    hammer_settings = choose_hammer(hammer, simulated_engineer=sim and auto,
                                    lab_settings=lab.hammer_settings() if lab is not None else None,
                                    has_lab=lab is not None, force_n=hammer_force_n, tolerance=hammer_tolerance,
                                    where=str(config_path))
    settings = SessionSettings(
        name=out.name, plan=PlanSettings(views, radius_m, elevation_deg, target_m), n_frames=n_frames,
        pretrigger_frames=pretrigger_frames, fps=fps,
        trigger=HammerTrigger(level_n=trigger_n, pretrigger_s=pretrigger_s, record_s=record_s),
        limits=QCLimits(force_band_n=force_band, min_tags=min_tags), max_attempts=max_attempts,
        static_photos=static_photos, hammer=hammer_settings)
    if sim:
        from odsplat.hil_sim import SceneSettings, SimBench, SimBenchSettings, SimCameraConfig, make_rig, parse_faults

        try:
            w, h = (int(v) for v in size.lower().split("x"))
        except ValueError:
            raise InputError("--size", f"expected WxH in pixels, e.g. 400x300; got {size!r}") from None
        scene = SceneSettings(floor_tag_size_m=floor_tag_m, texture=texture)
        sim_settings = SimBenchSettings(width_px=w, height_px=h, seed=seed, structure=structure, scene=scene,
                                        camera=SimCameraConfig(fps=2000.0, bit_depth=bit_depth))
        bench = SimBench(make_rig(structure, scene, seed=seed), sim_settings,
                         faults=parse_faults(sim_faults), hammer=hammer_link if hammer_settings else None)
        if not auto:
            bench.place_camera = _asking_place(bench.place_camera)
            bench.decide = _asking_decide
    else:
        bench = LabBench(lab.open_camera(), lab.daq_url, lab.channels, lab.sample_rate_hz, lab.tags,
                         ask=lambda q: click.prompt(q, default="", show_default=False), tell=click.echo,
                         hammer=lab.open_hammer() if hammer_settings else None,
                         can=lab.can, open_can=lab.open_can if lab.can is not None else None)
    if window is None:
        window = display_available() and not auto
    feedback = PlotFeedback(click.echo, settings and _plan(settings)) if window else TextFeedback(click.echo)
    try:
        report = CaptureSession(out, settings, bench, feedback=feedback).run()
    finally:
        bench.close()  # SimBench and LabBench: the hammer's driver, the CAN bus, the simulated devices
    click.echo(report.summary())
    if not report.complete:
        sys.exit(1)


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--method", type=click.Choice(["auto", "ttl", "image"]), default="auto", show_default=True,
              help="Frame timing: the exposure strobe (ttl), the trigger frame refined by the images, "
                   "or ttl where recorded.")
@click.option("--all-takes", is_flag=True,
              help="Sync every take, complete or recovered after a crash, whatever QC said (default: those QC "
                   "accepted).")
@click.option("--normalize-impulse", is_flag=True, help="Scale each take's motion to the median hammer impulse.")
@click.option("--frames/--no-frames", default=True, show_default=True,
              help="Write the aligned frames to derived/sync/.")
@click.option("--image-check/--no-image-check", default=True, show_default=True,
              help="Date strobe-timed takes from the images too, as a check.")
@click.option("--trigger-delay-s", type=float, default=0.0, show_default=True,
              help="The camera's latency from the trigger edge to latching it.")
@click.option("--max-memory-mb", type=float, default=256.0, show_default=True, help="Working memory per take.")
@click.option("--plot/--no-plot", default=True, show_default=True, help="Write derived/sync.png.")
@click.option("--workers", type=int, default=None, help="Processes aligning the takes' frames (default: one per "
              "core).")
def sync(capture_dir: Path, method: str, all_takes: bool, normalize_impulse: bool, frames: bool, image_check: bool,
         trigger_delay_s: float, max_memory_mb: float, plot: bool, workers: int | None) -> None:
    """Put the takes of CAPTURE_DIR on one impact-locked timeline: derived/sync.json and the aligned frames."""
    _, result = _stage(capture_dir, "sync", _given(
        method="method", all_takes=("takes", lambda v: "all" if v else "accepted"),
        normalize_impulse="normalize_impulse", frames="write_frames", image_check="check_with_image",
        trigger_delay_s="camera_trigger_delay_s", max_memory_mb="max_memory_mb", plot="plot", workers="workers"))
    click.echo(result.summary())
    if not result.ok:
        sys.exit(1)


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--method", type=click.Choice(["phase", "linear", "learned"]), default="phase", show_default=True)
@click.option("--alpha", type=float, default=20.0, show_default=True, help="Output motion = alpha x input motion.")
@click.option("--band", "band_hz", type=float, nargs=2, default=None, metavar="LOW HIGH",
              help="Temporal band in Hz (default: static, against the first frame).")
@click.option("--filter", "filter_kind", type=click.Choice(["ideal", "fir", "butter", "diff_iir", "none"]),
              default=None, help="Temporal filter for the band (default: butter).")
@click.option("--mode", type=click.Choice(["static", "dynamic"]), default="static", show_default=True,
              help="Learned method without a band: against the first frame, or the previous one.")
@click.option("--source", type=click.Choice(["auto", "aligned", "raw"]), default="auto", show_default=True,
              help="sync's aligned frames, or the raw takes (auto: aligned when synced).")
@click.option("--workers", type=int, default=None, help="Parallel processes (default: one per core).")
@click.option("--take", "takes", multiple=True, help="Only these takes (repeatable).")
@click.option("--option", "options", multiple=True, metavar="KEY=VALUE",
              help="A keyword of the method (e.g. n_orientations=8, cutoff_wavelength_px=4); repeatable.")
@click.option("--video/--no-video", default=True, show_default=True, help="Write NAME.mp4 beside each take.")
@click.option("--video-fps", type=float, default=30.0, show_default=True, help="The mp4s' playback rate.")
@click.option("--side-by-side", is_flag=True, help="The mp4s show the input beside the magnified frames.")
def magnify(capture_dir: Path, method: str, alpha: float, band_hz, filter_kind: str | None, mode: str, source: str,
            workers: int | None, takes: tuple[str, ...], options: tuple[str, ...], video: bool, video_fps: float,
            side_by_side: bool) -> None:
    """Magnify the motion in every view of CAPTURE_DIR into derived/magnified/METHOD/ (frames, and an mp4 to watch);
    warns where alpha x the measured motion passes the method's bound."""
    from odsplat.processing import parse_options

    _, result = _stage(capture_dir, "magnify", _given(
        method="method", alpha="alpha", band_hz="band_hz", filter_kind="filter", mode="mode", source="source",
        workers="workers", takes="takes", options=("options", lambda v: [list(kv) for kv in parse_options(v)]),
        video="video", video_fps="video_fps", side_by_side="side_by_side"))
    click.echo(result.summary())


@main.command("export-video")
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--take", default=None, help="The take (default: every take of the source).")
@click.option("--source", default="raw", show_default=True,
              help="raw (the take), sync (on sync's common grid) or magnified/METHOD.")
@click.option("-o", "--out", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="The mp4 to write, one take only; must not exist (default: derived/videos/SOURCE/TAKE.mp4).")
@click.option("--fps", type=float, default=30.0, show_default=True,
              help="Playback rate (the recorded rate goes in the file's comment).")
def export_video(capture_dir: Path, take: str | None, source: str, out: Path | None, fps: float) -> None:
    """Write a take's raw, aligned or magnified frames to an 8-bit mp4 to watch (docs/processing.md)."""
    from odsplat.processing import check_export, export_video, source_takes
    from odsplat.spine.errors import InputError

    cap = _open(capture_dir)
    check_export(cap, take or "", source, out, fps)
    check_number("--fps", fps, PLAYBACK_FPS)
    takes = [take] if take else source_takes(cap, source)
    if out is not None and len(takes) != 1:
        raise InputError("-o", f"one file for {len(takes)} takes: name one with --take")
    for name in takes:
        with _locked(cap):
            done = export_video(cap, name, source, out, fps)
        v = done.mp4
        click.echo(f"{name}: {v.n_frames} frames {v.width_px}x{v.height_px} px ({source}) -> {v.path} "
                   f"({v.bytes / 1e6:.2f} MB, {v.codec}, {v.fps:g} frames/s; recorded at {done.recorded_fps:g})")


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--no-static", is_flag=True, help="Leave out the still photos in static/.")
@click.option("--estimate-intrinsics", is_flag=True,
              help="Refine the manifest's intrinsics instead of holding them fixed.")
@click.option("--masks", "masks_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of mask PNGs, TAKE.png and static/PHOTO.png; black = no features there.")
@click.option("--min-registered", type=int, default=3, show_default=True,
              help="Fewer images registered by SfM: fall back to poses from the tags alone.")
@click.option("--from", "from_file", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Known cameras: a TOML/JSON file of per-view name, K, R, t (world to camera, metres).")
def poses(capture_dir: Path, no_static: bool, estimate_intrinsics: bool, masks_dir: Path | None,
          min_registered: int, from_file: Path | None) -> None:
    """Camera poses of every view of CAPTURE_DIR in metres, floor z = 0: derived/poses.json, derived/points.npz."""
    cap, result = _stage(capture_dir, "poses", _given(
        no_static=("use_static", lambda v: not v),
        estimate_intrinsics=("fixed_intrinsics", lambda v: False if v else None),
        masks_dir=("masks_dir", str), min_registered="min_registered", from_file=("from_file", str)))
    for line in result.report_lines():
        click.echo(line)
    click.echo(f"wrote {cap.paths.poses_json} and {cap.paths.points_npz}")


@main.command("train-mm")
@click.option("-o", "--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="Weights file to write (its resumable checkpoint goes beside it as OUT.ckpt).")
@click.option("--steps", type=int, default=20000, show_default=True)
@click.option("--minutes", "max_minutes", type=float, default=None, help="Stop after this much wall time.")
@click.option("--batch-size", type=int, default=8, show_default=True)
@click.option("--crop", type=int, default=64, show_default=True, help="Training patch side in pixels (multiple of 4).")
@click.option("--lr", type=float, default=5e-4, show_default=True)
@click.option("--channels", type=int, default=16, show_default=True, help="Network width.")
@click.option("--threads", type=int, default=1, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--resume", is_flag=True, help="Continue from OUT.ckpt.")
def train_mm(out: Path, steps: int, max_minutes: float | None, batch_size: int, crop: int, lr: float, channels: int,
             threads: int, seed: int, resume: bool) -> None:
    """Train the learned motion magnifier (Oh et al. 2018) on procedural synthetic data
    (docs/magnification-learned.md)."""
    from odsplat.processing import TrainConfig, train

    report = train(TrainConfig(out=out, steps=steps, max_minutes=max_minutes, batch_size=batch_size, crop=crop, lr=lr,
                               channels=channels, threads=threads, seed=seed, resume=resume))
    click.echo(f"{report.steps} steps in {report.wall_s:.0f} s: validation SSIM {report.val_ssim:.3f} "
               f"(do nothing {report.val_ssim_frame_b:.3f}), PSNR {report.val_psnr:.2f} dB, "
               f"gain {report.val_gain:.2f}; "
               f"weights {report.out}")


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--source", default=None,
              help="Frames to fit: 'sync' (unmagnified, on the common grid) or 'magnified/METHOD'. Default: "
                   "sync, or magnified/phase for --motion timestep.")
@click.option("--width", "width_px", type=int, default=128, show_default=True, help="Training image width in px.")
@click.option("--timesteps", "n_timesteps", type=int, default=None,
              help="Timesteps to fit from the rest frame on (default: the whole record, at most 512, for the linear "
                   "and modal models; 32 for timestep).")
@click.option("--step", type=int, default=1, show_default=True, help="Grid frames between timesteps.")
@click.option("--start", type=int, default=None, help="First grid frame (default: the last before the impact).")
@click.option("--holdout", multiple=True, help="A take never used in training (repeatable).")
@click.option("--no-static", is_flag=True, help="Do not condition the t=0 fit on static photos.")
@click.option("--motion", type=click.Choice(["linear", "modal", "timestep"]), default="linear", show_default=True,
              help="linear: every timestep in one linear solve on the raw frames at full resolution, magnified in "
                   "3D at render time; modal: one temporal basis for every Gaussian, all timesteps at once; "
                   "timestep: a fit per timestep on frames magnified in 2D (Luiten et al.). docs/reconstruction.md "
                   "compares them: linear measures best.")
@click.option("--iters-t0", type=int, default=1500, show_default=True, help="Iterations of the rest fit.")
@click.option("--iters-modal", type=int, default=2000, show_default=True, help="Iterations of the modal fit.")
@click.option("--components", type=int, default=4, show_default=True, help="Temporal basis functions (modal).")
@click.option("--iters-step", "iters_per_step", type=int, default=150, show_default=True,
              help="Iterations per timestep (timestep).")
@click.option("--threads", type=int, default=None, help="Torch threads (default: torch's).")
@click.option("--seed", type=int, default=0, show_default=True)
def reconstruct(capture_dir: Path, source: str | None, width_px: int, n_timesteps: int | None, step: int,
                start: int | None, holdout: tuple[str, ...], no_static: bool, motion: str, iters_t0: int,
                iters_modal: int, components: int, iters_per_step: int, threads: int | None, seed: int) -> None:
    """Train dynamic 3D Gaussians on CAPTURE_DIR's posed views into derived/reconstruction/ (docs/reconstruction.md)."""
    _, result = _stage(capture_dir, "reconstruct", _given(
        source="source", width_px="width_px", n_timesteps="n_timesteps", step="step", start="start",
        holdout="holdout", no_static=("use_static", lambda v: not v), motion="motion", iters_t0="fit.iters_t0",
        iters_modal="modal.iters", components="modal.n_components", iters_per_step="fit.iters_per_step",
        threads="threads", seed=("fit.seed", "modal.seed")))
    click.echo(result.summary())


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--camera", "camera_spec", default="orbit", show_default=True,
              help="A take name (its estimated pose), orbit[:N[:ELEVATION_DEG[:DISTANCE_M]]], or a JSON camera path.")
@click.option("--times", "times_spec", default="all", show_default=True,
              help="'all' (the trained timesteps), 'A:B:N' (N times from A to B s) or 'a,b,c' (s after the impact).")
@click.option("-o", "--out", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder for the PNG frames and render.mp4 (default: derived/reconstruction/render/).")
@click.option("--width", "width_px", type=int, default=None, help="Image width in px (default: the camera's).")
@click.option("--alpha", type=float, default=None,
              help="Magnification to show (default: as trained, i.e. the frames' own). Scales every Gaussian's "
                   "displacement and rotation from rest: any factor, no retraining.")
@click.option("--fps", type=float, default=30.0, show_default=True, help="Frame rate of the mp4.")
@click.option("--no-mp4", is_flag=True)
def render(capture_dir: Path, camera_spec: str, times_spec: str, out: Path | None, width_px: int | None,
           alpha: float | None, fps: float, no_mp4: bool) -> None:
    """Render the reconstruction of CAPTURE_DIR from any camera path over any time range."""
    from odsplat.reconstruction import DynamicScene, camera_path, check_camera_spec, parse_times, render_sequence

    # alpha 0 shows the rest state; above, the 2D magnification's bound (MAGNIFICATION), so one number rules both.
    check_number("--alpha", alpha, maybe(Range(at_least=0, at_most=MAX_MAGNIFICATION)))
    check_number("--width", width_px, maybe(WIDTH_PX))
    check_number("--fps", fps, PLAYBACK_FPS)
    cap = _open(capture_dir)
    check_camera_spec(camera_spec)
    scene = DynamicScene.load(cap)
    times = parse_times(times_spec, scene.times_s)
    cameras = camera_path(cap, camera_spec, len(times), width_px)
    with _locked(cap):
        paths = render_sequence(scene, cameras, times, out or cap.paths.render_dir, alpha=alpha, fps=fps,
                                mp4=not no_mp4)
    click.echo(f"{sum(p.suffix == '.png' for p in paths)} frames -> {paths[0].parent}"
               + (f" (and {paths[-1].name})" if paths and paths[-1].suffix == ".mp4" else ""))


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--force", "force_channel", default=None,
              help="Force channel (default: the capture's one force channel).")
@click.option("--response", "responses", multiple=True,
              help="Response channel (repeatable; default: every acceleration channel placed on the structure).")
@click.option("--all-takes", is_flag=True,
              help="Use every take, complete or recovered after a crash, whatever QC said (default: those QC "
                   "accepted). A recovered take holds what was flushed before the crash; `odsplat info` marks it.")
@click.option("--fmin", "fmin_hz", type=float, default=None, help="Modal fit band, low end (Hz).")
@click.option("--fmax", "fmax_hz", type=float, default=None,
              help="Modal fit band, high end (Hz; default 0.45 x the frame rate, or 0.4 x the DAQ rate).")
@click.option("--max-order", type=int, default=None,
              help="Highest LSCF model order (default: 120, at most half the fit band's frequency lines).")
@click.option("--freq", "approx_freq_hz", type=float, multiple=True,
              help="Pick the pole nearest this frequency (repeatable) instead of automatic selection.")
@click.option("--ods", "ods_freq_hz", type=float, multiple=True,
              help="An ODS frequency line (repeatable; default: the modal frequencies).")
@click.option("--exp-end", type=float, default=0.01, show_default=True,
              help="Exponential window: its value at the end of the record (0: rectangular).")
@click.option("--record", "record_s", type=float, default=None, help="Seconds of each hit to use (default: all).")
@click.option("--no-video", is_flag=True, help="Accelerometers only, even with a reconstruction.")
@click.option("--image-poles/--no-image-poles", default=True, show_default=True,
              help="Also find poles in the synced takes' raw frames (needs a few hundred ms of frames for low modes).")
@click.option("--plots/--no-plots", default=True, show_default=True,
              help="Write the figures and each mode's animation (derived/analysis/plots/), which the report shows.")
@click.option("--report/--no-report", "with_report", default=True, show_default=True,
              help="Also write derived/analysis/report.html.")
def analyze(capture_dir: Path, force_channel: str | None, responses: tuple[str, ...], all_takes: bool,
            fmin_hz: float | None, fmax_hz: float | None, max_order: int | None, approx_freq_hz: tuple[float, ...],
            ods_freq_hz: tuple[float, ...], exp_end: float, record_s: float | None, no_video: bool,
            image_poles: bool, plots: bool, with_report: bool) -> None:
    """FRFs, modes, the video's 3D shapes and their correlation for CAPTURE_DIR, into derived/analysis/
    (docs/analysis.md)."""
    from odsplat.spine.errors import InputError

    if not 0 <= exp_end < 1:
        raise InputError("--exp-end", f"expected 0 (rectangular) up to below 1; got {exp_end}")
    cap, result = _stage(capture_dir, "analyze", _given(
        force_channel="force_channel", responses="response_channels",
        all_takes=("takes", lambda v: "all" if v else "accepted"), fmin_hz="fmin_hz", fmax_hz="fmax_hz",
        max_order="max_order", approx_freq_hz="approx_freq_hz", ods_freq_hz="ods_freq_hz",
        exp_end=("frf.exponential_end", lambda v: v or None), record_s="record_s",
        no_video=("video", lambda v: not v), image_poles="image_poles", plots="plots"))
    click.echo(result.text())
    if with_report:
        _, path = _stage(capture_dir, "report", {})
        click.echo(f"report -> {path}")


@main.command()
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
def report(capture_dir: Path) -> None:
    """Write derived/analysis/report.html from the last `odsplat analyze` of CAPTURE_DIR."""
    _, path = _stage(capture_dir, "report", {})
    click.echo(path)


@main.command()
@click.argument("out", type=click.Path(path_type=Path), default="demo-out", required=False)
@click.option("--quick", is_flag=True, help="The same steps at a small scale (8 views, 40 frames, a coarse "
                                            "reconstruction): about a minute and a half.")
@click.option("--shared-data", type=click.Path(path_type=Path), default=None,
              help="The folder of real recordings (default: $ODSPLAT_SHARED_DATA, else ../shared/data when it "
                   "exists; without it that part is skipped).")
@click.option("--seed", type=int, default=None,
              help="The simulated capture's noise and hammer scatter (default 0): the same demo on another draw.")
def demo(out: Path, quick: bool, shared_data: Path | None, seed: int | None) -> None:
    """Run the demo into OUT (default demo-out): a guided 27-view capture on the simulated rig with faults that QC
    catches, the whole pipeline, a magnified orbit render and the report (OUT/sim-rig, made anew on each run), then
    the real LADISK recordings imported and analysed (OUT/ladisk-beam). Prints each capture's modes and MAC, the
    reports and the viewer command."""
    from odsplat.app.demo import run_demo

    result = run_demo(out, quick=quick, shared_data=shared_data, echo=click.echo, seed=seed)
    click.echo("")
    click.echo(result.text())


@main.command()
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--export", "export_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Write the view as an .mp4 or .gif instead of opening the window.")
@click.option("--screenshot", "screenshot_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Write the view as a PNG instead of opening the window.")
@click.option("--frames", "n_frames", type=int, default=48, show_default=True, help="Frames of the export.")
@click.option("--fps", type=float, default=24.0, show_default=True, help="Frame rate of the export.")
@click.option("--alpha", type=float, default=100.0, show_default=True,
              help="Magnification in 3D, 1 to 1000 (displacements and rotations from rest times alpha).")
@click.option("--mode", "mode_number", type=int, default=None,
              help="Animate mode K (1-based, the analysis's numbering) at its frequency; the export is one cycle.")
@click.option("--ods", "ods_number", type=int, default=None,
              help="Animate ODS line K (1-based, the analysis's lines) at its frequency, per newton of harmonic force.")
@click.option("--motion", is_flag=True, help="The measured motion over the reconstruction's time (the default).")
@click.option("--time", "time_s", type=float, default=None, help="Time in s after the impact (screenshot).")
@click.option("--turntable", is_flag=True, help="The export's camera turns once around the structure.")
@click.option("--camera", "camera_index", type=int, default=None, help="Look through capture camera N.")
@click.option("--structure-only", is_flag=True, help="Hide what does not move (the floor, the background).")
@click.option("--colour", type=click.Choice(["image", "displacement"]), default="image", show_default=True,
              help="The Gaussians' own colours, or their displacement amplitude (with a scale bar).")
@click.option("--size", "size_px", type=(int, int), default=(640, 480), show_default=True,
              help="Image width and height in px.")
def view(capture_dir: Path, export_path: Path | None, screenshot_path: Path | None, n_frames: int, fps: float,
         alpha: float, mode_number: int | None, ods_number: int | None, motion: bool, time_s: float | None,
         turntable: bool, camera_index: int | None, structure_only: bool, colour: str,
         size_px: tuple[int, int]) -> None:
    """Look at CAPTURE_DIR's result: the Gaussians magnified in 3D, the modes, the FRFs and the signals linked
    (a window), or write the view as a video or a screenshot (--export, --screenshot)."""
    from dataclasses import replace

    from odsplat.app.viewer import default_state, export_video, load_viewer, save_screenshot
    from odsplat.app.viewer.model import ALPHA_RANGE
    from odsplat.spine.errors import InputError

    # The window's magnification slider spans ALPHA_RANGE (1 to 1000, within MAGNIFICATION); its frames box 10000.
    check_number("--alpha", alpha, Range(at_least=ALPHA_RANGE[0], at_most=ALPHA_RANGE[1]))
    check_number("--frames", n_frames, Range(at_least=1, at_most=10_000, integer=True))
    check_number("--fps", fps, PLAYBACK_FPS)
    if min(size_px) < 8 or max(size_px) > 8192:
        raise InputError("--size", f"expected 8 to 8192 px each way, got {size_px[0]} x {size_px[1]}")
    if sum(x is not None and x is not False for x in (mode_number, ods_number, motion or None)) > 1:
        raise InputError("--mode", "give one of --mode K, --ods K or --motion")
    data = load_viewer(capture_dir)
    state = default_state(data, alpha=alpha, structure_only=structure_only, colour=colour, width_px=size_px[0],
                          height_px=size_px[1])
    if mode_number is not None or ods_number is not None:
        kind, option, number = ("mode", "--mode", mode_number) if ods_number is None else ("ods", "--ods", ods_number)
        index = [k for k, m in enumerate(data.modes) if m.kind == kind]
        if not 1 <= number <= len(index):
            raise InputError(option, f"expected {'a mode' if kind == 'mode' else 'an ODS line'} from 1 to "
                                     f"{len(index)}, got {number}")
        state = replace(state, mode=index[number - 1], time_s=0.0)
    elif motion:
        if data.scene is None:
            raise InputError("--motion", "no reconstruction: only the modes can be shown (--mode K)")
        state = replace(state, mode=None, time_s=data.time_range_s[0])
    if time_s is not None:
        state = replace(state, time_s=time_s)
    if camera_index is not None:
        if not 0 <= camera_index < len(data.cameras):
            raise InputError("--camera", f"expected a capture camera from 0 to {len(data.cameras) - 1}, got "
                                         f"{camera_index}")
        state = replace(state, snap=camera_index)
    for note in data.notes:
        click.echo(f"note: {note}", err=True)
    if export_path is not None or screenshot_path is not None:
        if screenshot_path is not None:
            click.echo(f"screenshot -> {save_screenshot(data, state, screenshot_path)}")
        if export_path is not None:
            path = export_video(data, state, export_path, n_frames=n_frames, fps=fps, turntable=turntable)
            click.echo(f"{n_frames} frames -> {path}")
        return
    from odsplat.acquisition import display_available

    if not display_available():
        raise InputError("display", "no display to open the window on (set DISPLAY, or use --export/--screenshot)")
    from odsplat.app.viewer.app import ViewerWindow

    window = ViewerWindow(data, state)
    sys.exit(window.run())


def _plan(settings):
    from odsplat.acquisition import plan_views

    return plan_views(settings.plan)


def _asking_place(place):
    def ask(view, instructions):
        place(view, instructions)
        click.prompt("The simulated camera is placed; press Enter to arm", default="", show_default=False)
    return ask


def _asking_decide(qc, pose) -> bool:
    return click.confirm(f"{qc.summary()}. Accept?", default=qc.accepted)


if __name__ == "__main__":
    main()
