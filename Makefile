# Two commands: `make demo` and `make test` (which runs `make lint` first). Both create or update .venv first.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out
SHARED_DATA ?= ../shared/data

.PHONY: demo test lint install bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# Reinstall when the dependency list or the pins change.
$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'
	# pyidi, the tests' and bench's reference tracker, without its dependencies: they would put OpenCV's GUI build
	# beside our headless one (both own cv2); what its Lucas-Kanade method needs is installed above.
	$(BIN)/python -m pip install -q --no-deps pyidi==1.4.0
	touch $@

install: $(STAMP)

test: $(STAMP) lint
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest

# `make test`'s pytest on a busy machine: tools/busy.py starts one busy loop per core, runs the suite beside them and
# stops them after (on Ctrl-C too), to check that no test depends on how fast the machine is (about 30 min on two
# cores). Speed is bench/'s to measure.
.PHONY: test-busy
test-busy: $(STAMP)
	$(BIN)/python tools/busy.py

# The house rules as checks: ruff ([tool.ruff] in pyproject.toml) and the import contracts ([tool.importlinter]: the
# stages import only the spine and each other's package __init__, the spine no stage). lint-imports runs on a copy
# laid out as installed (tools/lint_imports.py), since grimp cannot follow the editable install's package-dir mapping.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python tools/lint_imports.py --no-logo

# The demo is `odsplat demo` (odsplat/app/demo.py): a guided 27-view capture on the simulated rig into
# $(DEMO_OUT)/sim-rig (256 frames per take at 2000 fps, with a rebound and a dropped packet injected, which QC
# rejects and the session redoes), the whole pipeline on it (`odsplat run`, with odsplat/examples/demo.toml as the
# capture's odsplat.toml), an orbit render magnified 30x in 3D, the report rewritten with the render, and the real
# LADISK recordings imported from $(SHARED_DATA) and run through the same pipeline when that folder exists. It ends
# with each capture's modes and MAC, the reports' paths and the viewer command. Rerunning it redoes the captures
# it made (never a folder it did not make); `odsplat demo --quick` is the same at a small scale.
# SHARED_DATA given (make demo SHARED_DATA=DIR) must exist; the default is used when it exists, else skipped.
demo: $(STAMP)
	$(BIN)/odsplat demo $(DEMO_OUT) $(if $(or $(wildcard $(SHARED_DATA)),$(filter-out file,$(origin SHARED_DATA))),--shared-data $(SHARED_DATA))

bench: $(STAMP)
	$(BIN)/python bench/store.py
	$(BIN)/python bench/render.py
	$(BIN)/python bench/render.py --scene rig --no-cold-compile
	$(BIN)/python bench/daq.py
	$(BIN)/python bench/sync.py
	$(BIN)/python bench/magnify.py
	$(BIN)/python bench/raster.py
	$(BIN)/python bench/reconstruct.py --sensitivity

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info
