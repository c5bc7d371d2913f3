"""odsplat: motion-magnified 3D operational deflection shapes from impact tests.

The spine: the capture store (the contract between the stages), configuration, the pipeline
and the command line. Each stage lives in its own subpackage, `odsplat.<stage>`.
"""
from __future__ import annotations

__version__ = "0.1.0"
