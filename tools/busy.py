"""Run the test suite on a busy machine: one busy-loop process per core beside `make test`'s pytest, to check that
no test depends on how fast the machine is (a test asserts behaviour; bench/ measures speed).

Usage: python tools/busy.py [--loops N] [-- PYTEST_ARGS...]; exits with pytest's status. Without PYTEST_ARGS it
runs what `make test` runs (`python -m pytest`: the options in pyproject.toml, QT_QPA_PLATFORM=offscreen), about
30 minutes on two cores. The loops stop when pytest ends, on Ctrl-C (which reaches pytest as in a terminal) and on
SIGTERM; each loop also ends by itself once this process is gone (killed, say), so none is left spinning.
Example, a small selection: python tools/busy.py -- tests/test_impulse.py -q -n 0
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import time

log = logging.getLogger("busy")

# A loop that spins until its parent (this script) is gone: then it is re-parented and stops by itself.
LOOP = """
import os
parent = os.getppid()
while os.getppid() == parent:
    for _ in range(1_000_000):
        pass
"""


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def start_loops(n: int) -> list[subprocess.Popen]:
    """n busy loops, each in a session of its own, so that a Ctrl-C at the terminal reaches pytest, not them."""
    return [subprocess.Popen([sys.executable, "-c", LOOP], stdin=subprocess.DEVNULL, start_new_session=True)
            for _ in range(n)]


def stop_loops(loops: list[subprocess.Popen], timeout_s: float = 5.0) -> None:
    """Terminate every loop (kill one that does not end within timeout_s) and reap it."""
    for p in loops:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + timeout_s
    for p in loops:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _on_sigterm(signum, frame) -> None:
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    own, pytest_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     usage="python tools/busy.py [--loops N] [-- PYTEST_ARGS...]")
    parser.add_argument("--loops", type=int, default=cores(),
                        help=f"busy loops to run beside pytest (default: one per core, {cores()} here)")
    args = parser.parse_args(own)
    if args.loops < 0:
        parser.error(f"--loops: expected 0 or more; got {args.loops}")
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="tools/busy.py: %(message)s")
    signal.signal(signal.SIGTERM, _on_sigterm)
    env = {**os.environ, "QT_QPA_PLATFORM": os.environ.get("QT_QPA_PLATFORM", "offscreen")}
    loops = start_loops(args.loops)
    pytest = None
    try:
        log.info("%d busy loop(s) on %d core(s) (pids %s); load average %.1f", len(loops), cores(),
                 " ".join(str(p.pid) for p in loops), os.getloadavg()[0])
        pytest = subprocess.Popen([sys.executable, "-m", "pytest", *pytest_args], env=env)
        while True:
            try:
                return pytest.wait()
            except KeyboardInterrupt:
                log.info("Ctrl-C: waiting for pytest to stop")  # pytest got the SIGINT too and ends its run
    finally:
        if pytest is not None and pytest.poll() is None:
            pytest.terminate()
            try:
                pytest.wait(30)
            except subprocess.TimeoutExpired:
                pytest.kill()
                pytest.wait()
        stop_loops(loops)
        log.info("stopped %d busy loop(s); load average %.1f", len(loops), os.getloadavg()[0])


if __name__ == "__main__":
    sys.exit(main())
