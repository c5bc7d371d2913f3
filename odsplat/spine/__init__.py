"""The spine: what every stage stands on and nothing of a stage's own.

The capture store: `store` (`Capture`, the capture's folder), `take_writer`, `take_reader` and `recovery` (the raw
takes: written once, read through their checksums, recovered after a crash), `atomic` (write, fsync, rename),
`paths` (every derived file's name), `contract` (the header each derived file carries), `manifest`, `framefile`,
`qcfile`, `integrity`. The shared numerics: `impulse` (the one impact rule), `timebase`, `geometry`, `tags`,
`similarity`, `units`. The readers of other vendors' files: `io`, `importer`. The safety rules: `guard`, `lock`,
`space`, `errors`, `checks`. It imports no stage and nothing of `odsplat.app` (the layers contract in
pyproject.toml).
"""
