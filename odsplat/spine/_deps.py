"""Imports put off until they are needed: pycolmap, after cv2 (the other order can hang cv2), and `resolve`, an
object named by its import path, which the application's stage table and acquisition's camera back ends use."""
from __future__ import annotations

import functools
import importlib
import logging
import sys
from types import ModuleType
from typing import Any

log = logging.getLogger(__name__)


def import_pycolmap() -> ModuleType:
    """Import pycolmap after cv2: the other order can make cv2's PNG writing hang.

    Every odsplat module that needs pycolmap gets it from here, never by `import pycolmap`.
    """
    if "pycolmap" in sys.modules and "cv2" not in sys.modules:
        log.warning("pycolmap was imported before cv2 outside odsplat; cv2's PNG writing may hang")
    import cv2  # noqa: F401  (the import order is the point)

    return importlib.import_module("pycolmap")


@functools.cache
def resolve(path: str) -> Any:
    """The object an import path names, "package.module:name", imported on first use."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)
