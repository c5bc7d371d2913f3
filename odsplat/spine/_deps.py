"""The one place where pycolmap is imported, after cv2, because the other order can hang cv2."""
from __future__ import annotations

import importlib
import logging
import sys
from types import ModuleType

log = logging.getLogger(__name__)


def import_pycolmap() -> ModuleType:
    """Import pycolmap after cv2: the other order can make cv2's PNG writing hang.

    Every odsplat module that needs pycolmap gets it from here, never by `import pycolmap`.
    """
    if "pycolmap" in sys.modules and "cv2" not in sys.modules:
        log.warning("pycolmap was imported before cv2 outside odsplat; cv2's PNG writing may hang")
    import cv2  # noqa: F401  (the import order is the point)

    return importlib.import_module("pycolmap")
