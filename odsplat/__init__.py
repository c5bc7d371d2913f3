"""odsplat: motion-magnified 3D operational deflection shapes from impact tests.

Three layers (docs/architecture.md): the spine, `odsplat.spine` (the capture store, the contract between the
stages, and the numerics they share); the stages, each its own subpackage `odsplat.<stage>` with its entry `run`;
and the application, `odsplat.app` (configuration, the pipeline, the command line, batch, demo, viewer).

In a notebook::

    import odsplat
    cap = odsplat.Capture.open("demo-out/sim-rig", derived="/tmp/scratch")   # leave the capture's derived/ alone
    odsplat.run(cap, odsplat.load_config(cap, sets=("magnify.alpha=50",)), stop="magnify")
    result = odsplat.sync.run(cap, odsplat.SyncSettings(write_frames=False))

Names are imported on first use: `import odsplat` stays light.
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    "Capture": "spine.store", "DerivedPaths": "spine.paths", "Provenance": "spine.contract",
    "Config": "app.config", "load_config": "app.config", "STAGES": "app.config",
    "run": "app.pipeline", "run_stage": "app.pipeline", "status": "app.pipeline", "PipelineResult": "app.pipeline",
    "QCSettings": "acquisition", "SyncSettings": "sync", "MagnifySettings": "processing",
    "PoseSettings": "reconstruction", "ReconstructSettings": "reconstruction", "AnalyzeSettings": "analysis",
}
_STAGES = ("acquisition", "sync", "processing", "reconstruction", "analysis", "hil_sim")

__all__ = sorted([*_EXPORTS, *_STAGES])


def __getattr__(name: str):
    if name in _STAGES:
        return importlib.import_module(f".{name}", __name__)
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
