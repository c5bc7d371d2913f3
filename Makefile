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
	touch $@

install: $(STAMP)

test: $(STAMP) lint
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest

# The house rules as checks: ruff ([tool.ruff] in pyproject.toml) and the import contracts ([tool.importlinter]: the
# stages import only the spine and each other's package __init__, the spine no stage). lint-imports runs on a copy
# laid out as installed (tools/lint_imports.py), since grimp cannot follow the editable install's package-dir mapping.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python tools/lint_imports.py --no-logo

# The demo runs what works end to end: a guided 27-view capture on the simulated rig (with two
# injected faults that QC catches and the session redoes), then the whole pipeline in one command
# (`odsplat run`, with examples/demo.toml as the capture's odsplat.toml): hit QC, sync of the takes onto
# one impact-locked timeline, phase-based magnification of every view (2D videos to watch), camera poses
# (pycolmap + tags), dynamic 3D Gaussians (the rest state at 128 px, then 64 timesteps of motion from the raw
# frames in one linear solve), the analysis (modes from the accelerometers, the video's 3D shapes, MAC,
# UFF/HDF5) and the report; then an orbit render magnified 30x in 3D, and the real LADISK recordings imported
# from $(SHARED_DATA) and run through the same pipeline (their known modes) when that folder exists.
demo: $(STAMP)
	rm -rf $(DEMO_OUT)/sim-rig
	$(BIN)/odsplat capture $(DEMO_OUT)/sim-rig --sim --auto --no-window --frames 100 --sim-faults 3:double_hit,9:dropped_packet
	$(BIN)/odsplat info $(DEMO_OUT)/sim-rig
	cp examples/demo.toml $(DEMO_OUT)/sim-rig/odsplat.toml
	$(BIN)/odsplat run $(DEMO_OUT)/sim-rig
	$(BIN)/odsplat render $(DEMO_OUT)/sim-rig --camera orbit:16:30 --times -0.0005:0.031:16 --alpha 30
	$(BIN)/odsplat report $(DEMO_OUT)/sim-rig
	@if test -d $(SHARED_DATA); then \
	  rm -rf $(DEMO_OUT)/ladisk-beam && \
	  $(BIN)/odsplat import examples/ladisk-beam.toml --data $(SHARED_DATA) -o $(DEMO_OUT)/ladisk-beam && \
	  $(BIN)/odsplat info $(DEMO_OUT)/ladisk-beam && \
	  $(BIN)/odsplat run $(DEMO_OUT)/ladisk-beam; \
	else echo "demo: $(SHARED_DATA) not found; skipping the import of real recordings (set SHARED_DATA=...)"; fi

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
