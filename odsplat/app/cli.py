"""The `odsplat` command line: `odsplat run` for the whole pipeline, and one thin command per stage calling the
same entry, made from the stage table (stages.py) with its options generated from the stage's settings (options.py);
errors are one line naming the culprit.

What a command needs of the stages, the viewer (Qt), the demo or the batch (Dask) it imports when it runs: three
stages load torch, and `odsplat --help`, `info`, `verify` and `qc` must start without it (the rule in stages.py).
The spine and the pipeline are light and imported here."""
from __future__ import annotations

import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from odsplat.app.budget import Budget, within_budget
from odsplat.app.config import STAGES, load_config, settings_type
from odsplat.app.options import (
    RENDER_FLAGS,
    STAGE_FLAGS,
    VIEW_FLAGS,
    Flag,
    SettingsCommand,
    blame,
    given,
    given_flags,
    lay_over,
    settings_from,
)
from odsplat.app.pipeline import frames_and_views, run, run_stage
from odsplat.app.pipeline import status as stage_status
from odsplat.app.stages import TABLE, Stage, resolve
from odsplat.spine.checks import PLAYBACK_FPS, WORKERS, check_number, maybe
from odsplat.spine.errors import InputError, OdsplatError, exit_if_hdf5_unclosed, quiet_hdf5_releases, storage_error
from odsplat.spine.integrity import listed_take_problems, verify_capture
from odsplat.spine.lock import capture_lock
from odsplat.spine.sensors import apply_geometry, geometry_toml, read_geometry
from odsplat.spine.store import Capture
from odsplat.spine.summary import summarize


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
    quiet_hdf5_releases()


def _set_wait(ctx: click.Context, _param: click.Parameter, value: bool) -> None:
    ctx.meta["odsplat.wait"] = value


def _set_derived(ctx: click.Context, _param: click.Parameter, value: Path | None) -> None:
    ctx.meta["odsplat.derived"] = value


_WAIT = (("--wait",), {
    "is_flag": True, "expose_value": False, "callback": _set_wait,
    "help": "When another odsplat command is writing this capture, wait for it to finish instead of stopping."})
_DERIVED = (("--derived",), {
    "type": click.Path(path_type=Path, file_okay=False), "default": None, "expose_value": False,
    "callback": _set_derived, "is_eager": True,
    "help": "Read and write the derived files in this folder instead of the capture's derived/ (a read-only "
            "capture, a faster disk)."})


def _wait_params() -> list[click.Parameter]:
    """--wait and --derived, for the commands that write a capture's derived files."""
    return [click.Option(list(decls), **kwargs) for decls, kwargs in (_WAIT, _DERIVED)]


def _wait_option(command):
    """--wait and --derived on a command (a decorator)."""
    for decls, kwargs in (_DERIVED, _WAIT):
        command = click.option(*decls, **kwargs)(command)
    return command


def _waits() -> bool:
    return bool(click.get_current_context().meta.get("odsplat.wait"))


def _open(capture_dir: Path):
    """The capture, with its derived files where --derived says."""

    return Capture.open(capture_dir, derived=click.get_current_context().meta.get("odsplat.derived"))


def _locked(capture: Any):
    """The capture's lock for a command that writes it outside the pipeline (recover, geometry, render)."""

    return capture_lock(capture, wait=_waits())


def _stage(capture_dir: Path, stage: str, flags: Sequence[Flag] = ()) -> tuple[Any, Any]:
    """Run one stage through the pipeline's entry: the capture's configuration with the flags given laid over it
    (the command line's layer, checked by the stage's settings as --set is). Returns (capture, the stage's result)."""

    cap = _open(capture_dir)
    config = lay_over(load_config(cap), stage, click.get_current_context(), flags)
    return cap, run_stage(cap, stage, config, wait=_waits()).result


def _settings(cls: type, flags: Sequence[Flag]) -> Any:
    """A command's settings (not a stage's) from the flags given, checked by the settings class."""
    ctx = click.get_current_context()
    return settings_from(cls, given(ctx, flags), given_flags(ctx, flags))


@main.command()
@click.argument("capture", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def info(capture: Path, as_json: bool) -> None:
    """Summarise a capture: takes, frames, channels, sizes and QC flags."""

    summary = summarize(capture)
    click.echo(json.dumps(summary.to_dict(), indent=2) if as_json else summary.to_text())


@main.command("import")
@click.argument("rig", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="New capture directory.")
@click.option("--data", type=click.Path(path_type=Path), default=None,
              help="Folder the rig's file names are relative to (default: the rig file's folder).")
def import_(rig: Path, out: Path, data: Path | None) -> None:
    """Build a capture from recordings of other equipment described by a RIG file (TOML, see docs/import.md)."""
    from odsplat.spine.importer import import_capture  # its readers load numba (pyMRAW)


    capture = import_capture(rig, out, data_dir=data)
    click.echo(f"imported {len(capture.manifest.takes)} takes into {capture.root}")


@main.command()
@_wait_option
@click.argument("capture", type=click.Path(path_type=Path))
def recover(capture: Path) -> None:
    """Recover takes left unfinished by a crash, keeping every flushed frame and sample."""

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

        click.echo("")
        for name, current, why in stage_status(cap, config):
            state = "n/a" if why.startswith("does not apply") else "current" if current else "stale"
            click.echo(f"# {name:<12} {state}: {why}")
        if cap.paths.poses_json.is_file():      # the defaults that follow the data, where the data are there
            poses = resolve("odsplat.reconstruction:PoseResult").read(cap)    # lazily: it loads torch (stages.py)
            width = resolve("odsplat.reconstruction:working_width")(poses, config.reconstruct)
            click.echo(f"# reconstruct.width_px = {width.width_px}: {width.why}")
        budget = Budget.of(config.run)
        click.echo(f"# run.memory_gb = {budget.bytes / 1e9:.1f}: {budget.why}")
        for name in ("sync", "magnify", "reconstruct"):
            _, line = within_budget(name, config.settings(name), budget, *frames_and_views(cap))
            if line:
                click.echo(f"#   {line}")


@main.command()
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--sim", is_flag=True, help="Capture from the simulated rig (hil_sim) instead of the lab's devices.")
@click.option("--auto", is_flag=True, help="On the simulated rig: the simulated engineer places, hits and accepts; no "
                                           "questions.")
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None,
              help="Lab configuration (TOML: DAQ port and channels, camera, tags; docs/acquisition.md). Its camera "
                   "driver names a back end: opencv, photron, or sim for the simulated rig.")
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
@click.option("--hit-timeout", "hit_timeout_s", type=float, default=60.0, show_default=True,
              help="Seconds to wait for the hit once the DAQ is armed; a take without one is redone.")
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
@click.option("--structure", default="arm", show_default=True,
              help="With --sim: the rig, 'arm', 'plate', 'frame' or 'mast'.")
@click.option("--texture", default="speckle", show_default=True,
              help="With --sim: the structure's texture, 'speckle', 'value_noise' or 'checker'.")
@click.option("--floor-tag-m", type=float, default=0.12, show_default=True,
              help="With --sim: the floor tags' size (m): 0.12 is ~20 px at 256x256.")
@click.option("--bit-depth", type=int, default=12, show_default=True,
              help="With --sim: 12 (in 16-bit words, as Photron writes them) or 8.")
@click.option("--window/--no-window", default=None, help="Live plots in a window (default: when a display exists).")
def capture(out: Path, sim: bool, auto: bool, config_path: Path | None, window: bool | None, **o: Any) -> None:
    """Guided multi-view capture into OUT: place the camera at each planned view, hit, QC, accept or redo.

    Stop at any time (even by a crash) and run the same command again to resume."""
    from odsplat.acquisition import (
        CaptureSession,
        PlotFeedback,
        TextFeedback,
        display_available,
        load_lab_config,
        open_bench,
    )

    if sim == (config_path is not None):
        raise InputError("odsplat capture", "give exactly one of --sim or --config LAB.toml")
    lab = load_lab_config(config_path) if config_path is not None else None
    simulated = lab is None or lab.simulated
    if auto and not simulated:
        raise InputError("odsplat capture", "--auto needs the simulated rig (--sim, or driver = \"sim\" in the lab "
                                            "file): in the lab a person places the camera and hits")
    settings = _session_settings(out, lab, simulated and auto, o, str(config_path))
    if window is None:
        window = display_available() and not auto
    feedback = PlotFeedback(click.echo, _plan(settings)) if window else TextFeedback(click.echo)
    bench = open_bench(lab, None if lab is not None else _sim_rig(o), hammer=settings.hammer is not None,
                       ask=lambda q: click.prompt(q, default="", show_default=False), tell=click.echo)
    if simulated and not auto:
        bench.place_camera = _asking_place(bench.place_camera)
        bench.decide = _asking_decide
    try:
        report = CaptureSession(out, settings, bench, feedback=feedback).run()
    finally:
        bench.close()  # the simulated rig and the lab: the hammer's driver, the CAN bus, the simulated devices
    click.echo(report.summary())
    if not report.complete:
        sys.exit(1)


def _session_settings(out: Path, lab: Any, engineer: bool, o: dict[str, Any], where: str) -> Any:
    """The capture session's settings from `odsplat capture`'s options `o` and the lab file's [hammer]."""
    from odsplat.acquisition import HammerTrigger, PlanSettings, QCLimits, SessionSettings, choose_hammer

    hammer = choose_hammer(o["hammer"], simulated_engineer=engineer,
                           lab_settings=lab.hammer_settings() if lab is not None else None,
                           has_lab=lab is not None and not lab.simulated, force_n=o["hammer_force_n"],
                           tolerance=o["hammer_tolerance"], where=where)
    return SessionSettings(
        name=out.name, plan=PlanSettings(o["views"], o["radius_m"], o["elevation_deg"], o["target_m"]),
        n_frames=o["n_frames"], pretrigger_frames=o["pretrigger_frames"], fps=o["fps"],
        trigger=HammerTrigger(level_n=o["trigger_n"], pretrigger_s=o["pretrigger_s"], record_s=o["record_s"]),
        limits=QCLimits(force_band_n=o["force_band"], min_tags=o["min_tags"]), max_attempts=o["max_attempts"],
        hit_timeout_s=o["hit_timeout_s"], static_photos=o["static_photos"], hammer=hammer)


def _sim_rig(o: dict[str, Any]) -> Any:
    """The simulated rig's settings from `odsplat capture --sim`'s options `o`."""
    from odsplat.acquisition import SimRigSettings

    try:
        width, height = (int(v) for v in o["size"].lower().split("x"))
    except ValueError:
        raise InputError("--size", f"expected WxH in pixels, e.g. 400x300; got {o['size']!r}") from None
    return SimRigSettings(size_px=(width, height), bit_depth=o["bit_depth"], seed=o["seed"], structure=o["structure"],
                          texture=o["texture"], floor_tag_m=o["floor_tag_m"], faults=o["sim_faults"],
                          hammer_link=o["hammer_link"])


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


@main.command("train-mm")
@click.option("-o", "--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="Weights file to write (its resumable checkpoint goes beside it as OUT.ckpt).")
@click.option("--steps", type=int, default=20000, show_default=True)
@click.option("--minutes", "max_minutes", type=float, default=None, help="Stop after this much wall time.")
@click.option("--batch-size", type=int, default=8, show_default=True)
@click.option("--crop", type=int, default=64, show_default=True, help="Training patch side in pixels (multiple of 4).")
@click.option("--lr", type=float, default=5e-4, show_default=True)
@click.option("--size", type=click.Choice(["small", "paper"]), default=None,
              help="A named network size: small (0.11 M parameters, shipped) or paper (0.87 M, Oh et al.'s).")
@click.option("--channels", type=int, default=16, show_default=True, help="Network width (without --size).")
@click.option("--threads", type=int, default=1, show_default=True)
@click.option("--device", default="cpu", show_default=True, help="Where the network trains: cpu, cuda.")
@click.option("--workers", type=int, default=0, show_default=True,
              help="Processes making the synthetic batches ahead of the network (0: in line).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--resume", is_flag=True, help="Continue from OUT.ckpt.")
@click.option("--init", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Start from these weights (of the same size) instead of at random: fine-tuning.")
def train_mm(out: Path, steps: int, max_minutes: float | None, batch_size: int, crop: int, lr: float,
             size: str | None, channels: int, threads: int, device: str, workers: int, seed: int,
             resume: bool, init: Path | None) -> None:
    """Train the learned motion magnifier (Oh et al. 2018) on procedural synthetic data
    (docs/magnification-learned.md). Writes OUT, its checkpoint OUT.ckpt and its log (OUT without .pt + .log.json)."""
    from odsplat.processing import TrainConfig, train

    report = train(TrainConfig(out=out, steps=steps, max_minutes=max_minutes, batch_size=batch_size, crop=crop, lr=lr,
                               size=size, channels=channels, threads=threads, device=device, workers=workers,
                               seed=seed, resume=resume, init=init))
    click.echo(f"{report.steps} steps in {report.wall_s:.0f} s: validation SSIM {report.val_ssim:.3f} "
               f"(do nothing {report.val_ssim_frame_b:.3f}), PSNR {report.val_psnr:.2f} dB, "
               f"gain {report.val_gain:.2f}; "
               f"weights {report.out}")


@main.command(cls=SettingsCommand, flags=RENDER_FLAGS, settings=lambda: resolve("odsplat.app.display:RenderSettings"))
@_wait_option
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("-o", "--out", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder for the PNG frames and render.mp4 (default: derived/reconstruction/render/).")
def render(capture_dir: Path, out: Path | None, **_: Any) -> None:
    """Render the reconstruction of CAPTURE_DIR from any camera path over any time range."""
    from odsplat.app.display import RenderSettings
    from odsplat.reconstruction import DynamicScene, camera_path, parse_times, render_sequence

    s = _settings(RenderSettings, RENDER_FLAGS)
    cap = _open(capture_dir)
    scene = DynamicScene.load(cap)
    times = parse_times(s.times, scene.times_s)
    cameras = camera_path(cap, s.camera, len(times), s.width_px)
    with _locked(cap):
        paths = render_sequence(scene, cameras, times, out or cap.paths.render_dir, alpha=s.alpha, fps=s.fps,
                                mp4=s.mp4)
    click.echo(f"{sum(p.suffix == '.png' for p in paths)} frames -> {paths[0].parent}"
               + (f" (and {paths[-1].name})" if paths and paths[-1].suffix == ".mp4" else ""))


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


@main.command(cls=SettingsCommand, flags=VIEW_FLAGS, settings=lambda: resolve("odsplat.app.display:ViewSettings"))
@click.argument("capture_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--export", "export_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Write the view as an .mp4 or .gif instead of opening the window.")
@click.option("--screenshot", "screenshot_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Write the view as a PNG instead of opening the window.")
def view(capture_dir: Path, export_path: Path | None, screenshot_path: Path | None, **_: Any) -> None:
    """Look at CAPTURE_DIR's result: the Gaussians magnified in 3D, the modes, the FRFs and the signals linked
    (a window), or write the view as a video or a screenshot (--export, --screenshot)."""
    from odsplat.app.display import ViewSettings, view_state
    from odsplat.app.viewer import export_video, load_viewer, save_screenshot

    s = _settings(ViewSettings, VIEW_FLAGS)
    if _view_2d(capture_dir, s, export_path, screenshot_path):
        return
    data = load_viewer(capture_dir)
    try:
        state = view_state(data, s)
    except InputError as exc:
        raise blame(exc, VIEW_FLAGS) from None
    for note in data.notes:
        click.echo(f"note: {note}", err=True)
    if screenshot_path is not None:
        click.echo(f"screenshot -> {save_screenshot(data, state, screenshot_path)}")
    if export_path is not None:
        path = export_video(data, state, export_path, n_frames=s.n_frames, fps=s.fps, turntable=s.turntable)
        click.echo(f"{s.n_frames} frames -> {path}")
    if export_path is not None or screenshot_path is not None:
        return
    from odsplat.acquisition import display_available

    if not display_available():
        raise InputError("display", "no display to open the window on (set DISPLAY, or use --export/--screenshot)")
    from odsplat.app.viewer.app import ViewerWindow

    sys.exit(ViewerWindow(data, state).run())


def _view_2d(capture_dir: Path, s: Any, export_path: Path | None, screenshot_path: Path | None) -> bool:
    """A capture the 2D path analysed (video2d.json, no analysis.json): its frame with a mode's 2D shape as a
    screenshot or one cycle as a video (viewer/view2d.py); False for any other capture."""
    from odsplat.analysis import has_video2d
    from odsplat.spine.store import Capture

    try:
        cap = Capture.open(capture_dir)
    except InputError:
        return False                         # load_viewer says what is wrong with it
    if cap.paths.analysis_json.exists() or not has_video2d(cap):
        return False
    from odsplat.app.viewer.view2d import export_2d, load_view2d, screenshot_2d

    if export_path is None and screenshot_path is None:
        raise InputError(capture_dir, "a capture the 2D path analysed (one camera, no force) has no 3D scene for the "
                                      "window; use --screenshot or --export (or open its report)")
    view = load_view2d(cap)
    try:
        if screenshot_path is not None:
            click.echo(f"screenshot -> {screenshot_2d(view, screenshot_path, s.mode)}")
        if export_path is not None:
            click.echo(f"{s.n_frames} frames -> {export_2d(view, export_path, s.mode, s.n_frames, s.fps)}")
    except InputError as exc:
        raise blame(exc, VIEW_FLAGS) from None
    return True


# ------------------------------------------------------------------------------------------ the stage commands

def _after_sync(ctx: click.Context, cap: Any, result: Any) -> None:
    if not result.ok:
        sys.exit(1)


def _after_poses(ctx: click.Context, cap: Any, result: Any) -> None:
    click.echo(f"wrote {cap.paths.poses_json} and {cap.paths.points_npz}")


def _after_analyze(ctx: click.Context, cap: Any, result: Any) -> None:
    if ctx.params["report"]:
        _, path = _stage(ctx.params["capture_dir"], "report")
        click.echo(f"report -> {path}")


_AFTER = {"sync": _after_sync, "poses": _after_poses, "analyze": _after_analyze}


def _stage_command(st: Stage) -> click.Command:
    """A stage's command, from the stage table: CAPTURE_DIR, --wait, --derived and the stage's flags (options.py,
    built from its settings class on first use); it runs the stage through the pipeline and prints its summary."""
    flags = STAGE_FLAGS.get(st.name, ())

    def callback(capture_dir: Path, **_: Any) -> None:
        cap, result = _stage(capture_dir, st.name, flags)
        click.echo(st.summary(result))
        if st.name in _AFTER:
            _AFTER[st.name](click.get_current_context(), cap, result)

    params = [*_wait_params(), click.Argument(["capture_dir"], type=click.Path(path_type=Path, file_okay=False))]
    if st.settings_path is None:
        return click.Command(st.name, callback=callback, params=params, help=st.doc)
    return SettingsCommand(st.name, callback=callback, params=params, help=st.doc, flags=flags,
                           settings=lambda: settings_type(st.name), prefix=st.name)


for _st in TABLE:
    main.add_command(_stage_command(_st))


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
