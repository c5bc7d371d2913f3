# Two commands: `make demo` and `make test`. Both create or update .venv first.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out
SHARED_DATA ?= ../shared/data

.PHONY: demo test install bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# Reinstall when the dependency list or the pins change.
$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'
	touch $@

install: $(STAMP)

test: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest

# Until the simulated rig and the later stages land, the demo is the part that works end to
# end: import real recordings into a capture and summarise it.
demo: $(STAMP)
	@test -d $(SHARED_DATA) || { echo "demo: the recordings folder $(SHARED_DATA) is missing (set SHARED_DATA=...)"; exit 1; }
	rm -rf $(DEMO_OUT)/ladisk-beam
	$(BIN)/odsplat import examples/ladisk-beam.toml --data $(SHARED_DATA) -o $(DEMO_OUT)/ladisk-beam
	$(BIN)/odsplat info $(DEMO_OUT)/ladisk-beam

bench: $(STAMP)
	$(BIN)/python bench/store.py
	$(BIN)/python bench/render.py
	$(BIN)/python bench/render.py --scene rig --no-cold-compile
	$(BIN)/python bench/daq.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info
