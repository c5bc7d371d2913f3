"""Processing: video motion magnification of every view, streamed in bounded memory.

Public surface: `run(capture, MagnifySettings)` (alias `magnify_capture`) -> `MagnifyResult`, saved to
`derived/magnified/METHOD/`; `MagnifiedVideo` reads a magnified take. Magnifiers and filters for use on their
own are in their modules."""
from .learned import TrainConfig, train
from .magnify import (
    METHODS,
    MagnifiedTake,
    MagnifiedVideo,
    MagnifyResult,
    MagnifySettings,
    magnify_capture,
    parse_options,
)

run = magnify_capture  # the stage's entry

__all__ = ["METHODS", "MagnifiedTake", "MagnifiedVideo", "MagnifyResult", "MagnifySettings", "magnify_capture",
           "parse_options", "run", "TrainConfig", "train"]
