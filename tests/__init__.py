"""The test suite. Importing it (pytest does before tests/conftest.py) sets what every test process shares.

Two xdist workers share two cores, and the tests' subprocesses (odsplat run, batch, demo) use every core too. An
OpenMP thread that waits for its team spins by default: with the cores oversubscribed it burns the time that the
thread it waits for needs (the modal fit ran 6x slower beside the pipeline's tests, and the suite took 14 min
instead of 10). Waiting threads sleep instead; subprocesses inherit it. It is set before torch loads its OpenMP
runtime, which reads it once."""
import os
import sys

assert "torch" not in sys.modules, "tests/__init__.py: torch was imported before OMP_WAIT_POLICY could be set"
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
