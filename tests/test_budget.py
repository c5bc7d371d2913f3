"""The run's memory budget (`[run] memory_gb`): the per-view stages' pools no wider than it holds, where their
workers are left unset; the results and the stages' currency the same under any budget."""
from __future__ import annotations

import logging

import pytest
from click.testing import CliRunner

from odsplat.app.budget import MAGNIFY_PER_PX, Budget, RunSettings, machine_memory_bytes, within_budget
from odsplat.app.cli import main
from odsplat.app.config import load_config
from odsplat.app.pipeline import is_current, run_stage
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture

from .conftest import piped_copy

PX_1024 = 1024 * 1024


def test_the_budget_narrows_a_pool_left_unset_and_warns_of_one_set_wider():
    magnify = load_config(sets=("magnify.every_view=true",)).magnify
    roomy = Budget(64e9, "as set")
    s, line = within_budget("magnify", magnify, roomy, PX_1024, 27)
    assert s.workers >= 1 and "of about 3.3" in line and "not" not in line
    tight = Budget(4e9, "as set")                  # one 1024^2 view's pyramid holds about 3.3 GB: one fits
    s, line = within_budget("magnify", magnify, tight, PX_1024, 27)
    assert s.workers == 1 and (MAGNIFY_PER_PX * PX_1024 < 4e9)
    assert "process of about" in line and ("not " in line or s.workers == 1)
    # too small for even one: one runs, and the line says it passes the budget
    s, line = within_budget("magnify", magnify, Budget(1e9, "as set"), PX_1024, 27)
    assert s.workers == 1 and "one alone passes the budget of 1.0 GB" in line
    # set by hand: kept, with a warning when wider than the budget holds
    by_hand = load_config(sets=("magnify.every_view=true", "magnify.workers=3")).magnify
    s, line = within_budget("magnify", by_hand, tight, PX_1024, 27)
    assert s.workers == 3 and "3 processes" in line and "1 fit" in line
    # sync's process holds what its own max_memory_mb allows
    sync = load_config(sets=("sync.max_memory_mb=1000",)).sync
    s, line = within_budget("sync", sync, Budget(2.5e9, "as set"), PX_1024, 27)
    assert s.workers == 1, line
    # the linear motion's readers: a chunk of 64 frames at 1024^2 is about 2.4 GB a process
    rec = load_config().reconstruct
    s, line = within_budget("reconstruct", rec, tight, PX_1024, 27)
    assert s.linear.workers == 1 and line.startswith("reconstruct: 1 process of about 2.")
    assert within_budget("reconstruct", rec, roomy, PX_1024, 27)[0].linear.workers >= 1
    # the other motion models, and the stages that stream in fixed chunks, are left as they are
    timestep = load_config(sets=("reconstruct.motion='timestep'",)).reconstruct
    assert within_budget("reconstruct", timestep, tight, PX_1024, 27) == (timestep, None)
    analyze = load_config().analyze
    assert within_budget("analyze", analyze, tight, PX_1024, 27) == (analyze, None)


def test_the_budget_is_a_setting_of_the_run_with_a_default_from_the_machine(tmp_path):
    assert Budget.of(RunSettings()).bytes == pytest.approx(0.5 * machine_memory_bytes())
    assert Budget.of(load_config(sets=("run.memory_gb=3",)).run).bytes == 3e9
    path = tmp_path / "odsplat.toml"
    path.write_text("[run]\nmemory_gb = 6.5\n")
    config = load_config(path=path)
    assert config.run.memory_gb == 6.5 and "[run]\nmemory_gb = 6.5" in config.to_toml()
    with pytest.raises(InputError, match="memory_gb"):
        load_config(sets=("run.memory_gb=0",))
    with pytest.raises(InputError, match="memory_gb"):
        load_config(sets=("run.memory_gb='lots'",))


def test_a_run_under_a_small_budget_runs_one_process_and_stays_current(piped_original, tmp_path, caplog):
    cap = Capture.open(piped_copy(piped_original, tmp_path / "cap"))
    defaults = tmp_path / "defaults.toml"          # not the piped capture's own, which sets magnify's workers
    defaults.write_text("")
    small = load_config(cap, path=defaults, sets=("run.memory_gb=0.5", "magnify.every_view=true"))
    assert is_current(cap, "sync", load_config(cap, sets=("run.memory_gb=0.5",)))[0]   # no setting of a result
    assert is_current(cap, "reconstruct", load_config(cap, sets=("reconstruct.linear.workers=3",)))[0]
    with caplog.at_level(logging.INFO, logger="odsplat.app.pipeline"):
        run_stage(cap, "magnify", small)
    assert any("magnify: 1 process of about" in r.getMessage() and "not " in r.getMessage() for r in caplog.records)
    assert is_current(cap, "magnify", load_config(cap, path=defaults, sets=("run.memory_gb=100",
                                                                           "magnify.every_view=true")))[0]
    out = CliRunner().invoke(main, ["config", str(cap.root), "--status", "--config", str(defaults), "--set",
                                    "run.memory_gb=0.5", "--set", "magnify.every_view=true"])
    assert out.exit_code == 0 and "# run.memory_gb = 0.5: as set (run.memory_gb)" in out.output
    assert "#   magnify: 1 process of about" in out.output
