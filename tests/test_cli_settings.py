"""The stage commands' options are generated from the settings dataclasses (odsplat/app/options.py), and tested here
from the settings themselves: for every flag, no flag gives the dataclass's default; every value a settings class
refuses (past a bound, not among its choices) is refused by the flag and by `--set STAGE.FIELD=VALUE` alike, exit 2,
in one line naming the flag or the field, with nothing written; and every value it accepts gives the same settings
by the flag as by --set. `render` and `view` likewise against their own settings classes."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import click
import pytest
import tomli_w
from click.testing import CliRunner

from odsplat.app.cli import main
from odsplat.app.config import Config, load_config, settings_type
from odsplat.app.options import (
    RENDER_FLAGS,
    STAGE_FLAGS,
    VIEW_FLAGS,
    Flag,
    field_default,
    field_of,
    given,
    lay_over,
    settings_from,
)
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import from_plain
from odsplat.spine.store import Capture

from .conftest import tiny_capture

# The flag values tried: past any bound either way, NaN, zero and small numbers, a word that is no choice, pairs in
# and out of order. A settings class decides which it refuses; the command line must agree with it.
NUMBERS = {float: ["-1e30", "1e30", "nan", "-1", "0", "0.5", "1", "3"], int: ["-1", "0", "1", "3", "64", str(10 ** 12)]}
WORDS = ["no-such-choice", "sync", "x"]
PAIRS = {float: [("-1", "1"), ("1", "1e30"), ("2", "1"), ("nan", "1"), ("10", "20")],
         int: [("-1", "1"), ("0", "8"), ("16", "12"), ("64", "48"), ("100000", "64")]}


def _flags(table: dict[str, tuple[Flag, ...]]) -> list[tuple[str, Flag]]:
    return [(stage, f) for stage, flags in table.items() for f in flags if f.fields]


STAGE_CASES = _flags(STAGE_FLAGS)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Capture:
    """A capture with one complete take of 10 tiny frames, a force and an acceleration channel: what the stage
    commands open before they read their settings."""
    return tiny_capture(tmp_path_factory.mktemp("cli_settings") / "cap")


def _option(command: str, flag: Flag):
    (param,) = [p for p in main.commands[command].params if p.name == flag.name]
    return param


def _values(command: str, flag: Flag) -> list[list[str]]:
    """The command-line values to try for a flag: words after the flag."""
    option = _option(command, flag)
    if option.is_flag:
        return [[]]
    kind = {"INTEGER": int, "FLOAT": float}.get(option.type.name.upper())
    if option.nargs == 2:
        return [list(pair) for pair in PAIRS[kind]]
    if flag.choices:
        return [[c] for c in (*flag.choices, "no-such-choice")]
    if isinstance(option.type, click.Path):
        return [["no-such-folder/x"]]
    if flag.metavar == "KEY=VALUE":
        return [["n_orientations=8"], ["n_orientations=many"], ["n_orientations=1e9"], ["no_such=1"]]
    return [[v] for v in NUMBERS[kind]] if kind else [[w] for w in WORDS]


def _field_value(command: str, flag: Flag, words: list[str]) -> Any:
    """What the flag puts into its field(s) for these words, as the command parses them."""
    ctx = main.commands[command].make_context(command, ["cap", _flag_word(flag), *words])
    table = given(ctx, [flag])
    for part in flag.fields[0].split("."):
        table = table[part]
    return table


def _flag_word(flag: Flag) -> str:
    return flag.decl.split("/")[0]


def _table(paths: tuple[str, ...], value: Any) -> dict[str, Any]:
    table: dict[str, Any] = {}
    for path in paths:
        *parents, last = path.split(".")
        node = table
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    return table


def _refusal(cls: type, flag: Flag, value: Any) -> InputError | None:
    """The settings class's own verdict on `value` in the flag's field(s): its refusal, or None."""
    try:
        from_plain(cls, _table(flag.fields, value), "direct")
    except InputError as exc:
        return exc
    return None


def _set_items(stage: str, flag: Flag, value: Any) -> list[str]:
    """--set items carrying `value` into the flag's fields, VALUE in TOML."""
    text = tomli_w.dumps({"v": value}).strip().removeprefix("v = ")
    return [f"{stage}.{path}={text}" for path in flag.fields]


def _one_line(result, root: Path, before: list[Path], names: tuple[str, ...]) -> str:
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("odsplat: error: "), result.output
    assert any(n in lines[0] for n in names), lines[0]
    assert "Traceback" not in result.output
    assert sorted(root.rglob("*")) == before, "something was written"
    return lines[0]


# ------------------------------------------------------------------------------------------ the stage commands

@pytest.mark.parametrize("stage", list(STAGE_FLAGS))
def test_no_flag_is_the_dataclass_default(small, stage):
    cls = settings_type(stage)
    flags = STAGE_FLAGS[stage]
    ctx = main.commands[stage].make_context(stage, [str(small.root)])
    assert lay_over(Config.defaults(), stage, ctx, flags).settings(stage) == cls()
    for flag in flags:
        option = _option(stage, flag)
        if not flag.fields:
            assert option.default == flag.default   # the command's own option (analyze --report)
            continue
        assert option.default is None, f"{stage} {flag.decl}: the one default is the dataclass's"
        assert option.help and f"{stage}.{flag.fields[0]}" in option.help
        default = field_default(cls, flag.fields[0])
        if isinstance(default, (int, float)) and not isinstance(default, bool) and not flag.is_flag:
            assert f"default: {default:g}" in option.help, option.help
        for path in flag.fields[1:]:
            assert field_default(cls, path) == default, f"{flag.decl} sets {flag.fields} to one value"


@pytest.mark.timeout(120)
@pytest.mark.parametrize("stage, flag", STAGE_CASES, ids=[f"{s}{f.flag}" for s, f in STAGE_CASES])
def test_the_flag_and_set_refuse_and_accept_what_the_settings_do(small, stage, flag):
    cls = settings_type(stage)
    root = small.root
    before = sorted(root.rglob("*"))
    refused = accepted = 0
    for words in _values(stage, flag):
        value = _field_value(stage, flag, words)
        refusal = _refusal(cls, flag, value)
        field = flag.fields[0].rsplit(".", 1)[-1]
        if refusal is not None:
            refused += 1
            r = CliRunner().invoke(main, [stage, str(root), _flag_word(flag), *words])
            line = _one_line(r, root, before, (flag.flag, field))
            assert refusal.problem.split(";")[0] in line, (line, refusal)
            if value is None:
                continue   # no TOML for it
            r = CliRunner().invoke(main, ["config", str(root), *(a for item in _set_items(stage, flag, value)
                                                                  for a in ("--set", item))])
            _one_line(r, root, before, (field,))
            continue
        accepted += 1
        ctx = main.commands[stage].make_context(stage, [str(root), _flag_word(flag), *words])
        by_flag = lay_over(Config.defaults(), stage, ctx, STAGE_FLAGS[stage]).settings(stage)
        if value is None:   # what --set cannot carry (TOML has no null): the setting left automatic
            assert _get(by_flag, flag.fields[0]) is None
            continue
        by_set = load_config(sets=tuple(_set_items(stage, flag, value))).settings(stage)
        assert by_flag == by_set, (words, by_flag, by_set)
        assert by_flag != cls() or _same_as_default(cls, flag, value), f"{words} changed nothing"
    bounded = _option(stage, flag).is_flag is False and flag.fields[0] not in _FREE.get(stage, ())
    assert accepted >= 1 and (refused >= 1 or not bounded), (accepted, refused)


def _get(settings: Any, path: str) -> Any:
    for part in path.split("."):
        settings = getattr(settings, part)
    return settings


def _same_as_default(cls: type, flag: Flag, value: Any) -> bool:
    default = _get(cls(), flag.fields[0])   # as the class makes it (reconstruct's source follows its motion)
    return value == default or (isinstance(default, tuple) and list(default) == value)


# Fields any word or number is fine for, as far as the settings can tell (channel and take names, a count of
# threads left to torch): the data decides later.
_FREE = {"magnify": ("takes",), "reconstruct": ("holdout",),
         "analyze": ("force_channel", "response_channels"), "poses": ("masks_dir", "from_file")}


def test_a_flag_that_cannot_be_true_names_the_flag_and_the_field(small):
    root = small.root
    before = sorted(root.rglob("*"))
    r = CliRunner().invoke(main, ["magnify", str(root), "--alpha", "-3"])
    line = _one_line(r, root, before, ("--alpha",))
    assert line == ("odsplat: error: --alpha: expected a finite number > 0 and <= 10000; got -3.0 "
                    "(MagnifySettings.alpha)")
    r = CliRunner().invoke(main, ["config", str(root), "--set", "magnify.alpha=-3"])
    assert _one_line(r, root, before, ("MagnifySettings.alpha",)).endswith(
        "MagnifySettings.alpha: expected a finite number > 0 and <= 10000; got -3.0")
    # two flags: the one whose field the settings refuse is named, the bound is the other's value
    r = CliRunner().invoke(main, ["analyze", str(root), "--fmax", "100", "--fmin", "500"])
    assert _one_line(r, root, before, ("--fmin",)).startswith("odsplat: error: --fmin: expected below fmax_hz=100")


def test_every_settings_flag_names_a_real_field_once():
    for table, classes in ((STAGE_FLAGS, {s: settings_type(s) for s in STAGE_FLAGS}),):
        for stage, flags in table.items():
            names = [f.name for f in flags]
            assert len(names) == len(set(names)), stage
            for flag in flags:
                for path in flag.fields:
                    field_of(classes[stage], path)   # raises for a field the class does not have


# ------------------------------------------------------------------------------------------ render and view

DISPLAY_CASES = [("render", f) for f in RENDER_FLAGS] + [("view", f) for f in VIEW_FLAGS]


def _display_class(command: str) -> type:
    from odsplat.app.display import RenderSettings, ViewSettings

    return {"render": RenderSettings, "view": ViewSettings}[command]


@pytest.mark.parametrize("command", ["render", "view"])
def test_render_and_view_defaults_are_their_settings(small, command):
    flags = RENDER_FLAGS if command == "render" else VIEW_FLAGS
    ctx = main.commands[command].make_context(command, [str(small.root)])
    assert settings_from(_display_class(command), given(ctx, flags), []) == _display_class(command)()
    assert all(_option(command, f).default is None for f in flags)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("command, flag", DISPLAY_CASES, ids=[f"{c}{f.flag}" for c, f in DISPLAY_CASES])
def test_render_and_view_flags_refuse_what_their_settings_do(small, command, flag):
    cls = _display_class(command)
    root = small.root
    before = sorted(root.rglob("*"))
    for words in _values(command, flag):
        value = _field_value(command, flag, words)
        refusal = _refusal(cls, flag, value)
        ctx = main.commands[command].make_context(command, [str(root), _flag_word(flag), *words])
        if refusal is None:
            s = settings_from(cls, given(ctx, (flag,)), [flag])
            assert getattr(s, flag.fields[0]) == (tuple(value) if isinstance(value, list) else value)
            continue
        r = CliRunner().invoke(main, [command, str(root), _flag_word(flag), *words])
        line = _one_line(r, root, before, (flag.flag,))
        assert line.startswith(f"odsplat: error: {flag.flag}: "), line


def test_view_settings_refuse_what_the_window_cannot_show():
    from odsplat.app.display import RenderSettings, ViewSettings
    from odsplat.app.viewer.model import ALPHA_RANGE

    assert ViewSettings(alpha=ALPHA_RANGE[1]).alpha == ALPHA_RANGE[1]
    for bad in ({"alpha": ALPHA_RANGE[0] / 2}, {"alpha": ALPHA_RANGE[1] * 2}, {"size_px": (4, 480)},
                {"mode": 1, "ods": 1}, {"colour": "sepia"}, {"n_frames": 0}):
        with pytest.raises(InputError, match=r"^ViewSettings\."):
            ViewSettings(**bad)
    assert dataclasses.replace(RenderSettings(), alpha=0.0).alpha == 0.0
    with pytest.raises(InputError, match="--camera"):
        RenderSettings(camera="orbit:0")


@dataclasses.dataclass
class _Documented:
    plain: int = 1              # the comment after a field
    wrapped: float = 2.0        # a comment that goes on
    #                             to the next line
    # a section comment, no field's
    bare: str = "x"
    stringed: bool = True
    """A string under the field."""


def test_the_help_is_the_fields_own_documentation():
    from odsplat.app.options import field_docs
    from odsplat.sync import SyncSettings

    assert field_docs(_Documented) == {"plain": "the comment after a field",
                                       "wrapped": "a comment that goes on to the next line",
                                       "stringed": "A string under the field."}
    assert field_docs(SyncSettings)["workers"].endswith("at most one per take (the results are the same with any "
                                                        "number)")
    help_text = _option("sync", next(f for f in STAGE_FLAGS["sync"] if f.flag == "--workers")).help
    assert help_text.startswith("Processes aligning the takes' frames") and "[sync.workers]" in help_text
