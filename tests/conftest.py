"""Shared fixtures: the real recordings in ../shared/data, skipped with a reason when absent; the bench scripts
as modules."""
from __future__ import annotations

import importlib.util
import os
import shutil
import sys
from pathlib import Path

import pytest
from filelock import FileLock

from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.hil_sim.camera import SimCameraConfig
from odsplat.spine.shared_data import shared_data_dir
from odsplat.spine.store import Capture

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """Test-sized tensors gain nothing from threads, and two OpenMP threads on two shared cores can stall for
    seconds (a thread waits on one that is descheduled). Code under test that wants threads sets its own."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real recordings made by others; tests that need it skip when it is absent."""
    path = shared_data_dir(REPO)
    if not path.is_dir():
        pytest.skip(f"real recordings not found at {path} (set ODSPLAT_SHARED_DATA to their folder)")
    return path


def pytest_addoption(parser):
    parser.addoption("--hardware", action="store_true", help="run tests that need a real device attached")


# The files that take longest (a minute or more on two cores), longest first: run first, so that pytest-xdist's
# workers (a file each, in collection order: pyproject's addopts keep it, `--no-loadscope-reorder`, where xdist would
# put the files with the most tests first) fill the rest of their time with the short ones instead of ending on one
# long file while the other worker idles (the order of a measured run: each file's seconds, setup included).
LONG_FILES = ("analysis/test_run.py", "test_batch.py", "test_data_safety.py", "test_demo.py",
              "analysis/test_sensorview.py", "test_video2d.py", "acquisition/test_session.py",
              "reconstruction/test_run.py", "analysis/test_imagepoles.py", "test_pipeline.py",
              "test_derived_corruption.py", "test_memory_flat.py", "reconstruction/test_poses.py", "test_fidelity.py",
              "processing/test_run.py", "reconstruction/test_linear.py", "processing/test_video.py",
              "sync/test_sync.py", "acquisition/test_auto_hammer.py", "reconstruction/test_modal.py",
              "test_reproducible.py", "test_mode_clips.py", "reconstruction/test_dynamic.py")


_missing = [f for f in LONG_FILES if not (REPO / "tests" / f).is_file()]
assert not _missing, f"tests/conftest.py: LONG_FILES names files that are gone: {_missing}"


def _long_first(item) -> int:
    path = item.path.relative_to(REPO / "tests").as_posix()
    return LONG_FILES.index(path) if path in LONG_FILES else len(LONG_FILES)


def pytest_collection_modifyitems(config, items):
    items.sort(key=_long_first)      # stable: each file's tests keep their order
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs real hardware; run with --hardware")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


# ------------------------------------------------------------------ one small capture on the simulated rig

FPS = 2000.0
TRIGGER_DELAY_S = 0.5 / FPS  # the simulated camera latches the trigger half a frame late, give or take
TRIGGER_JITTER_S = 0.2 / FPS


@pytest.fixture(scope="session")
def sim_capture(tmp_path_factory) -> Capture:
    """Four views on the simulated rig, each at its own random frame phase, with a trigger that lags and
    jitters, hits that vary by 30 % in force; the second take a double hit, the fourth drops two frames
    (both redone). Six takes, about 15 s."""
    out = tmp_path_factory.mktemp("sync") / "cap"
    camera = SimCameraConfig(fps=FPS, trigger_delay_s=TRIGGER_DELAY_S, trigger_jitter_s=TRIGGER_JITTER_S)
    report = simulate_capture(out, n_views=4, n_frames=60, pretrigger_frames=10, record_s=0.2,
                              settings=SimBenchSettings(camera=camera, force_scatter=0.3, seed=3),
                              faults={1: "double_hit", 3: "dropped_frames"})
    assert report.complete
    return Capture.open(out)


def tiny_capture(out: Path) -> Capture:
    """A capture with one complete take of 10 frames of 8x8 px and a force and an acceleration channel: what a
    command opens before it reads its settings."""
    import numpy as np

    from odsplat.spine.manifest import ChannelInfo, Manifest

    cap = Capture.create(out, Manifest(name="s", daq_sample_rate_hz=1000.0, channels=[
        ChannelInfo("force", "force", "N"), ChannelInfo("acc", "acceleration", "m/s^2")]))
    with cap.new_take("a", view=1, frame_shape=(8, 8), dtype=np.uint8, fps=500.0) as w:
        for k in range(10):
            w.append_frames(np.full((8, 8), k, np.uint8))
        w.append_samples({"force": np.zeros(100), "acc": np.zeros(100)})
        w.finalize()
    return cap


def load_bench(name: str):
    """bench/NAME.py as a module (the bench is scripts, not a package), loaded once per process."""
    if f"bench_{name}" in sys.modules:
        return sys.modules[f"bench_{name}"]
    spec = importlib.util.spec_from_file_location(f"bench_{name}", REPO / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module          # a dataclass in it looks its module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def bench_script():
    """Load bench/NAME.py as a module: bench_script("analysis") (`load_bench`)."""
    return load_bench


# ------------------------------------------------------------------ a small capture through the whole pipeline

# Test-sized settings for `odsplat run`: 64 px Gaussians, few iterations, a low LSCF order for 24-frame (12 ms)
# takes, no 2D cross-check, triangulation or figures (tests/analysis covers them).
SMALL_PIPELINE_CONFIG = """
[magnify]
workers = 1
[reconstruct]
width_px = 64
n_timesteps = 16
[reconstruct.fit]
iters_t0 = 150
[analyze]
max_order = 30
image_poles = false
crosscheck_views = 0
triangulate_views = 0
plots = false
[report]
mode_clips = false
"""


def small_piped_capture(out: Path, *, n_views: int = 8, seed: int = 1) -> Path:
    """`n_views` views of 24 frames with static photos on the simulated rig, through `odsplat run` once (about
    40 s for 8 views): every derived file. What `odsplat run` printed is kept beside the capture (RUN_OUTPUT)."""
    from click.testing import CliRunner

    from odsplat.acquisition import CaptureSession, HammerTrigger, PlanSettings, SessionSettings
    from odsplat.app.cli import main
    from odsplat.hil_sim import SimBench

    session = SessionSettings(name="cap", plan=PlanSettings(n_views=n_views), n_frames=24, pretrigger_frames=4,
                              trigger=HammerTrigger(pretrigger_s=0.01, record_s=0.05), static_photos=True)
    assert CaptureSession(out, session, SimBench(settings=SimBenchSettings(seed=seed))).run().complete
    (out / "odsplat.toml").write_text(SMALL_PIPELINE_CONFIG)
    r = CliRunner().invoke(main, ["run", str(out)])
    assert r.exit_code == 0, r.output + repr(r.exception)
    (out.parent / RUN_OUTPUT).write_text(r.output)
    return out


RUN_OUTPUT = "run-output.txt"


@pytest.fixture(scope="session")
def piped_original(tmp_path_factory) -> Path:
    """The one small piped capture of the session (`small_piped_capture`, 8 views, seed 1), built once for every
    pytest-xdist worker: the first to ask builds it under a file lock in the workers' common base folder, the others
    wait and take it. Never change it: `piped_copy` gives a test module its own."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = shared / "piped-original"
    with FileLock(str(shared / "piped-original.lock")):
        if not (folder / "complete").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            small_piped_capture(folder / "cap")
            (folder / "complete").touch()
    return folder / "cap"


def piped_copy(original: Path, dest: Path) -> Path:
    """A copy of the session's piped capture at `dest` (a folder that does not exist yet), to change at will; what
    `odsplat run` printed building it is at dest.parent / RUN_OUTPUT."""
    shutil.copytree(original, dest, symlinks=True)
    shutil.copy2(original.parent / RUN_OUTPUT, dest.parent / RUN_OUTPUT)
    return dest
