"""The spine: what every stage stands on and nothing of a stage's own.

The capture store (`store`: the raw takes and `Capture`; `paths`: every derived file's name; `contract`: the
header each derived file carries; `manifest`, `framefile`, `integrity`), the shared numerics (`impulse`: the one
impact rule; `timebase`, `geometry`, `tags`, `similarity`, `units`), the readers of other vendors' files (`io`,
`importer`), and the safety rules (`guard`, `lock`, `space`, `errors`, `checks`). It imports no stage and nothing
of `odsplat.app` (the layers contract in pyproject.toml).
"""
