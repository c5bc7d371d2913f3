"""The application: the layer over the stages that runs them for an engineer.

`stages` (the one table of the stages: settings, entry, inputs, outputs; the one place that loads a stage on first
use), `config` (odsplat.toml and --set over the settings' defaults), `pipeline` (what is stale, run in order,
stamps), `cli` (the `odsplat` command) with `options` (its stage commands' flags, generated from the settings
dataclasses) and `display` (the render and view settings), `batch` (many captures over Dask), `demo`, and `viewer`.
Nothing below imports it (the layers contract in pyproject.toml).
"""
