"""The application: the layer over the stages that runs them for an engineer.

`config` (odsplat.toml and --set), `stages` (the one table of the stages: settings, entry, inputs, outputs),
`pipeline` (what is stale, run in order, stamps), `cli` (the `odsplat` command), `batch` (many captures over Dask),
`demo`, and `viewer`. Nothing below imports it (the layers contract in pyproject.toml).
"""
