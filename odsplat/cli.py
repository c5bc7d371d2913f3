"""The `odsplat` command line: one subcommand per working stage; errors are one line naming the culprit."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import click

from .errors import OdsplatError


class _Group(click.Group):
    """Turns odsplat's own errors into one line on stderr and exit status 2, with no traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except OdsplatError as exc:
            click.echo(f"odsplat: error: {exc}", err=True)
            sys.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
@click.version_option(package_name="odsplat")
def main(verbose: int) -> None:
    """odsplat: motion-magnified 3D operational deflection shapes from impact tests."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


@main.command()
@click.argument("capture", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def info(capture: Path, as_json: bool) -> None:
    """Summarise a capture: takes, frames, channels, sizes and QC flags."""
    from .summary import summarize

    summary = summarize(capture)
    click.echo(json.dumps(summary.to_dict(), indent=2) if as_json else summary.to_text())


@main.command("import")
@click.argument("rig", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="New capture directory.")
@click.option("--data", type=click.Path(path_type=Path), default=None,
              help="Folder the rig's file names are relative to (default: the rig file's folder).")
def import_(rig: Path, out: Path, data: Path | None) -> None:
    """Build a capture from recordings of other equipment described by a RIG file (TOML, see docs/import.md)."""
    from .importer import import_capture

    capture = import_capture(rig, out, data_dir=data)
    click.echo(f"imported {len(capture.manifest.takes)} takes into {capture.root}")


@main.command()
@click.argument("capture", type=click.Path(path_type=Path))
def recover(capture: Path) -> None:
    """Recover takes left unfinished by a crash, keeping every flushed frame and sample."""
    from .store import Capture

    cap = Capture.open(capture)
    reports = cap.recover()
    if not reports:
        click.echo("nothing to recover")
    for r in reports:
        click.echo(f"{r.name}: {'recovered' if r.recovered else 'NOT recovered'}: {r.message}")
    if any(not r.recovered for r in reports):
        sys.exit(1)


if __name__ == "__main__":
    main()
