"""Command-line options generated from the settings dataclasses.

Each command that sets a settings dataclass (the stage commands, `render`, `view`) has a declarative list of
`Flag`s: the flag, the settings field it sets and what click needs besides (nargs, a metavar, a flag pair, a
repeatable option, the choices to show, a conversion of the value). The click options are built from it when the
command is first used (`SettingsCommand`: `odsplat --help` imports no stage), with the field's documentation as
their help (the comment after the field in its class's source, or a string under it) and the dataclass's default
shown. The options themselves default to None and check nothing: a flag given goes into the settings table as
`--set` does (for a stage, the configuration's command-line layer), and the settings dataclass checks it, so the
flag, `--set` and odsplat.toml refuse the same values with the same line, which names the flag (`blame`).
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import re
import textwrap
import tokenize
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from click.core import ParameterSource

from odsplat.spine.errors import InputError
from odsplat.spine.manifest import from_plain

if TYPE_CHECKING:
    from odsplat.app.config import Config


@dataclass(frozen=True)
class Flag:
    """One option of a command: its flag and the settings field(s) it sets (None: the command's own option)."""

    decl: str                                  # "--alpha", or a pair "--frames/--no-frames"
    field: str | tuple[str, ...] | None        # "alpha", "fit.iters_t0", or several fields set to the same value
    nargs: int | None = None                   # default: the field's (2 for a (low, high) pair)
    metavar: str | None = None
    is_flag: bool = False                      # a flag alone (a bool field's single flag is one anyway)
    multiple: bool | None = None               # repeatable; default: for a field of any number of values
    choices: tuple[str, ...] = ()              # shown in the help; the settings dataclass checks them
    convert: Callable[[Any], Any] | None = None   # the option's value -> the field's (a flag that says it otherwise)
    help: str | None = None                    # instead of the field's documentation
    type: Any = None                           # click's type where the field's does not say it
    default: Any = None                        # the command's own option only: its default

    @property
    def fields(self) -> tuple[str, ...]:
        return () if self.field is None else (self.field,) if isinstance(self.field, str) else self.field

    @property
    def name(self) -> str:
        """The parameter's name, as click makes it from the (first) flag."""
        return self.decl.split("/")[0].lstrip("-").replace("-", "_")

    @property
    def flag(self) -> str:
        return self.decl.split("/")[0]


def _not(value: bool) -> bool:
    return not value


def _all_takes(value: bool) -> str:
    return "all" if value else "accepted"


def _magnifier_options(items: tuple[str, ...]) -> list[list[Any]]:
    from odsplat.processing import parse_options  # when the flag is given: processing loads torch (cli.py's rule)

    return [list(kv) for kv in parse_options(items)]


_TAKES = Flag("--all-takes", "takes", is_flag=True, convert=_all_takes,
              help="Every take, complete or recovered after a crash, whatever QC said (default: those QC accepted). "
                   "A recovered take holds what was flushed before the crash; `odsplat info` marks it.")

# The stage commands' flags, by stage. Help comes from the field's comment where `help` is not given.
STAGE_FLAGS: dict[str, tuple[Flag, ...]] = {
    "qc": (Flag("--force-band", "force_band_n", metavar="LOW HIGH"),),
    "sync": (
        Flag("--method", "method", choices=("auto", "ttl", "image")),
        _TAKES,
        Flag("--normalize-impulse", "normalize_impulse"),
        Flag("--frames/--no-frames", "write_frames"),
        Flag("--image-check/--no-image-check", "check_with_image"),
        Flag("--trigger-delay-s", "camera_trigger_delay_s"),
        Flag("--max-memory-mb", "max_memory_mb"),
        Flag("--plot/--no-plot", "plot"),
        Flag("--workers", "workers"),
    ),
    "magnify": (
        Flag("--method", "method", choices=("phase", "linear", "learned")),
        Flag("--alpha", "alpha"),
        Flag("--band", "band_hz", metavar="LOW HIGH"),
        Flag("--filter", "filter", choices=("ideal", "fir", "butter", "diff_iir", "none")),
        Flag("--mode", "mode", choices=("static", "dynamic")),
        Flag("--source", "source", choices=("auto", "aligned", "raw")),
        Flag("--workers", "workers"),
        Flag("--take", "takes"),
        Flag("--view", "views", multiple=True, type=int, help="Magnify this view's takes (repeatable; default: the "
             "first view's, unless the reconstruction reads magnified frames)."),
        Flag("--every-view", "every_view", is_flag=True, help="Magnify every view's takes."),
        Flag("--option", "options", multiple=True, metavar="KEY=VALUE", convert=_magnifier_options,
             help="A keyword of the method (e.g. n_orientations=8, cutoff_wavelength_px=4); repeatable."),
        Flag("--video/--no-video", "video"),
        Flag("--video-fps", "video_fps"),
        Flag("--side-by-side", "side_by_side"),
    ),
    "poses": (
        Flag("--no-static", "use_static", is_flag=True, convert=_not, help="Leave out the still photos in static/."),
        Flag("--estimate-intrinsics", "fixed_intrinsics", is_flag=True, convert=lambda v: False if v else None,
             help="Refine the manifest's intrinsics instead of holding them fixed."),
        Flag("--masks", "masks_dir", type=click.Path(file_okay=False)),
        Flag("--min-registered", "min_registered"),
        Flag("--from", "from_file", type=click.Path(dir_okay=False)),
    ),
    "reconstruct": (
        Flag("--source", "source"),
        Flag("--width", "width_px"),
        Flag("--timesteps", "n_timesteps"),
        Flag("--step", "step"),
        Flag("--start", "start"),
        Flag("--holdout", "holdout"),
        Flag("--no-static", "use_static", is_flag=True, convert=_not,
             help="Do not condition the t=0 fit on static photos."),
        Flag("--motion", "motion", choices=("linear", "modal", "timestep")),
        Flag("--iters-t0", "fit.iters_t0"),
        Flag("--iters-modal", "modal.iters"),
        Flag("--components", "modal.n_components"),
        Flag("--iters-step", "fit.iters_per_step"),
        Flag("--threads", "threads"),
        Flag("--seed", ("fit.seed", "modal.seed"), help="Random seed of the fits."),
    ),
    "analyze": (
        Flag("--force", "force_channel"),
        Flag("--response", "response_channels", help="Response channel (repeatable; default: every acceleration "
                                                      "channel placed on the structure)."),
        _TAKES,
        Flag("--fmin", "fmin_hz"),
        Flag("--fmax", "fmax_hz"),
        Flag("--max-order", "max_order"),
        Flag("--freq", "approx_freq_hz", help="Pick the pole nearest this frequency (repeatable) instead of "
                                              "automatic selection."),
        Flag("--ods", "ods_freq_hz", help="An ODS frequency line (repeatable; default: the modal frequencies)."),
        Flag("--exp-end", "frf.exponential_end", convert=lambda v: v or None,
             help="Exponential window: its value at the end of the record (0: rectangular)."),
        Flag("--record", "record_s"),
        Flag("--no-video", "video", is_flag=True, convert=_not, help="Accelerometers only, even with a "
                                                                     "reconstruction."),
        Flag("--image-poles/--no-image-poles", "image_poles"),
        Flag("--plots/--no-plots", "plots"),
        Flag("--report/--no-report", None, default=True, help="Also write derived/analysis/report.html."),
    ),
    "report": (
        Flag("--clips/--no-clips", "mode_clips"),
        Flag("--clip-frames", "clip_frames"),
        Flag("--clip-size", "clip_size_px", metavar="W H"),
    ),
}

# `odsplat render`'s and `odsplat view`'s flags, onto display.RenderSettings and display.ViewSettings.
RENDER_FLAGS: tuple[Flag, ...] = (
    Flag("--camera", "camera"),
    Flag("--times", "times"),
    Flag("--width", "width_px"),
    Flag("--alpha", "alpha"),
    Flag("--fps", "fps"),
    Flag("--no-mp4", "mp4", is_flag=True, convert=_not, help="The PNG frames only, no render.mp4."),
)
VIEW_FLAGS: tuple[Flag, ...] = (
    Flag("--frames", "n_frames"),
    Flag("--fps", "fps"),
    Flag("--alpha", "alpha"),
    Flag("--mode", "mode", metavar="K"),
    Flag("--ods", "ods", metavar="K"),
    Flag("--motion", "motion"),
    Flag("--time", "time_s"),
    Flag("--turntable", "turntable"),
    Flag("--camera", "camera", metavar="N"),
    Flag("--structure-only", "structure_only"),
    Flag("--surface", "surface"),
    Flag("--colour", "colour", choices=("image", "displacement")),
    Flag("--size", "size_px", metavar="W H"),
)


# ------------------------------------------------------------------------------------------ the settings fields

def _unwrap(hint: Any) -> Any:
    """X from X | None."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0] if len(args) == 1 else hint
    return hint


def field_of(cls: type, path: str) -> tuple[type, dataclasses.Field, Any]:
    """The dataclass a dotted field path ends in, that field and its type: ("fit.iters_t0" -> FitSettings, ...)."""
    *parents, last = path.split(".")
    for part in parents:
        cls = _unwrap(typing.get_type_hints(cls)[part])
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if last not in fields:
        raise KeyError(f"{cls.__name__} has no field {last!r}")
    return cls, fields[last], typing.get_type_hints(cls)[last]


def field_default(cls: type, path: str) -> Any:
    """A field's default as its dataclass declares it (None where a setting is left automatic)."""
    _, f, _ = field_of(cls, path)
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def field_docs(cls: type) -> dict[str, str]:
    """Each field's documentation from its class's source: the comment after it, with the comment lines below that
    continue it (at the same column), or else a string just under it."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[int, tuple[int, str, bool]] = {}   # line -> (column, text, alone on its line)
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            column = tok.start[1]
            comments[tok.start[0]] = (column, tok.string, not tok.line[:column].strip())
    body = ast.parse(source).body[0].body   # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for i, node in enumerate(body):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        end = node.end_lineno or node.lineno
        first = comments.get(end)
        if first is not None and not first[2]:
            column, text, _ = first
            parts = [text[1:].strip()]
            line = end + 1
            while line in comments and comments[line][2]:
                c, t, _ = comments[line]
                start = c + 1 + len(t[1:]) - len(t[1:].lstrip())   # where its words start
                if not (c == column or abs(start - (column + 2)) <= 1):
                    break
                parts.append(t[1:].strip())
                line += 1
            docs[node.target.id] = " ".join(p for p in parts if p)
        elif (i + 1 < len(body) and isinstance(body[i + 1], ast.Expr)
              and isinstance(getattr(body[i + 1], "value", None), ast.Constant)
              and isinstance(body[i + 1].value.value, str)):   # type: ignore[attr-defined]
            docs[node.target.id] = " ".join(body[i + 1].value.value.split())   # type: ignore[attr-defined]
    return docs


def _shown_default(value: Any, flag: Flag) -> str | None:
    """The default as the help shows it; None where nothing is worth showing (unset, a flag left off)."""
    if value is None or value == ():
        return None
    if isinstance(value, bool):
        if "/" not in flag.decl:
            return None
        on, off = flag.decl.split("/")
        return on if value else off
    if isinstance(value, (tuple, list)):
        return " ".join(_shown_default(v, flag) or "" for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


# ------------------------------------------------------------------------------------------ the click options

def _kind(flag: Flag, hint: Any) -> dict[str, Any]:
    """Click's type, nargs and multiple for a flag onto a field of type `hint` (empty for a flag alone)."""
    inner = _unwrap(hint)
    if "/" in flag.decl or flag.is_flag or (inner is bool and flag.convert is None):
        return {"is_flag": True}
    kind, nargs, multiple = inner, 1, False
    if typing.get_origin(inner) is tuple:
        args = typing.get_args(inner)
        if len(args) == 2 and args[1] is Ellipsis:
            kind, multiple = _unwrap(args[0]), True
        else:
            kind, nargs = _unwrap(args[0]), len(args)
    kind = flag.type or (click.Path() if kind is Path else kind if kind in (int, float, str) else str)
    return {"type": kind, "nargs": flag.nargs or nargs,
            "multiple": flag.multiple if flag.multiple is not None else multiple}


def _option(flag: Flag, cls: type | None, prefix: str | None) -> click.Option:
    """The click option of one flag, from the settings class `cls` (`prefix`: the stage, for --set's name)."""
    hint: Any = None
    doc, tail = flag.help, ""
    if flag.fields:
        owner, f, hint = field_of(cls, flag.fields[0])
        doc = doc or field_docs(owner).get(f.name)
        shown = None if flag.is_flag and flag.convert else _shown_default(field_default(cls, flag.fields[0]), flag)
        setting = " ".join(f"{prefix}.{p}" for p in flag.fields) if prefix else None
        tail = "; ".join(x for x in (setting, f"default: {shown}" if shown else None) if x)
    elif flag.default is not None:
        tail = f"default: {_shown_default(flag.default, flag)}"
    kind = _kind(flag, hint)
    if doc and re.match(r"[a-z]+ ", doc):   # a sentence, not a value ("auto: ...") or a path
        doc = doc[0].upper() + doc[1:]
    if doc and kind.get("multiple") and "repeatable" not in doc:
        doc += " (repeatable)"
    help_text = f"{doc} [{tail}]" if doc and tail else doc or (f"[{tail}]" if tail else None)
    metavar = "[" + "|".join(flag.choices) + "]" if flag.choices else flag.metavar
    return click.Option([flag.decl], default=flag.default if flag.field is None else None, metavar=metavar,
                        help=help_text, **kind)


def build_params(flags: Sequence[Flag], cls: type, prefix: str | None = None) -> list[click.Option]:
    """The click options of these flags, from settings class `cls`."""
    return [_option(flag, cls, prefix) for flag in flags]


class SettingsCommand(click.Command):
    """A command whose settings options are built on first use (its help, its parse), from a settings class that
    is imported then: listing the commands (`odsplat --help`) imports no stage."""

    def __init__(self, *args: Any, flags: Sequence[Flag], settings: Callable[[], type], prefix: str | None = None,
                 **kwargs: Any):
        self.flags = tuple(flags)
        self._settings = settings
        self._prefix = prefix
        self._built: list[click.Parameter] | None = None
        self._fixed: list[click.Parameter] = []
        super().__init__(*args, **kwargs)

    @property   # type: ignore[override]
    def params(self) -> list[click.Parameter]:
        if self._built is None:
            self._built = [*self._fixed, *build_params(self.flags, self._settings(), self._prefix)]
        return self._built

    @params.setter
    def params(self, value: list[click.Parameter]) -> None:
        self._fixed, self._built = list(value), None


# ------------------------------------------------------------------------------------------ from flags to settings

def given(ctx: click.Context, flags: Sequence[Flag]) -> dict[str, Any]:
    """The settings the flags given on the command line set (not those left at their default), as a table:
    {field: value, sub: {field: value}}, each value as --set would carry it."""
    table: dict[str, Any] = {}
    for flag in flags:
        if not flag.fields or ctx.get_parameter_source(flag.name) not in (ParameterSource.COMMANDLINE,
                                                                             ParameterSource.ENVIRONMENT):
            continue
        value = ctx.params[flag.name]
        value = flag.convert(value) if flag.convert else value
        for path in flag.fields:
            *parents, last = path.split(".")
            node = table
            for part in parents:
                node = node.setdefault(part, {})
            node[last] = list(value) if isinstance(value, tuple) else value
    return table


def given_flags(ctx: click.Context, flags: Sequence[Flag]) -> list[Flag]:
    return [f for f in flags if f.fields and ctx.get_parameter_source(f.name) in (ParameterSource.COMMANDLINE,
                                                                                   ParameterSource.ENVIRONMENT)]


def blame(error: InputError, flags: Sequence[Flag]) -> InputError:
    """The settings' refusal of a value the command line gave, naming the flag that gave it (`flags`: those given)
    first and the setting after: `--alpha: expected ...; got inf (MagnifySettings.alpha)`."""
    if error.source.startswith("-"):
        return error
    for flag in flags:
        names = {path.rsplit(".", 1)[-1] for path in flag.fields}
        if any(re.search(rf"(^|[^\w]){re.escape(n)}($|[^\w])", error.source) for n in names):
            if error.source in names:
                return InputError(flag.flag, error.problem)
            return InputError(flag.flag, f"{error.problem} ({error.source})")
    return error


def lay_over(config: Config, stage: str, ctx: click.Context, flags: Sequence[Flag]) -> Config:
    """The configuration with the stage's flags given on the command line laid over it, as the command line's layer
    (the same path as --set: the stage's settings class checks it); a refusal names the flag."""
    table = given(ctx, flags)
    if not table:
        return config
    try:
        return config.updated({stage: table}, "the command line")
    except InputError as exc:
        raise blame(exc, given_flags(ctx, flags)) from None


def settings_from(cls: type, table: dict[str, Any], flags: Sequence[Flag], where: str = "the command line") -> Any:
    """Settings of class `cls` (not a stage's: render's, view's) from the flags' table, checked by the class, a
    refusal naming the flag."""
    try:
        return from_plain(cls, table, where)
    except InputError as exc:
        raise blame(exc, flags) from None


__all__ = ["RENDER_FLAGS", "STAGE_FLAGS", "VIEW_FLAGS", "Flag", "SettingsCommand", "blame", "build_params",
           "field_default", "field_docs", "field_of", "given", "given_flags", "lay_over", "settings_from"]
