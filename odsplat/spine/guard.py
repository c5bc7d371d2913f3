"""Where odsplat may write and delete: inside a capture, through no symbolic link.

Recorded takes are the one thing the tool may never lose, and a capture is a folder that users copy, edit and
link by hand. A link planted in `derived/` (`derived/sync -> ../takes`) would turn the clean-up of a stage's stale
outputs into the deletion of the raw takes, and its writes into writes outside the capture. So odsplat makes no
link itself and goes through none: a capture that holds one is refused with one line naming it, before a stage
runs (`refuse_links`, called by `Capture.open`), every derived path is checked again as it is named
(`check_inside`, by `DerivedPaths`), and the deleting helpers delete only plain files they name themselves,
refusing a link with the same line (`link_error`).
"""
from __future__ import annotations

import os
from pathlib import Path

from odsplat.spine.errors import InputError

REFUSAL = ("a symbolic link{to}: odsplat reads and writes a capture only through its own files and folders, "
           "never through a link (replace the link by the folder or file itself, or give the stage --derived DIR)")


def link_error(path: Path) -> InputError:
    """The one refusal of a symbolic link in a capture, naming it and where it points."""
    try:
        target = f" (to {os.readlink(path)})"
    except OSError:
        target = ""
    return InputError(path, REFUSAL.format(to=target))


def lexically_inside(root: Path, path: Path) -> bool:
    """Whether `path`, with `..` folded away but no link followed, lies in `root` or is `root`."""
    root_abs = os.path.normpath(os.path.abspath(root))
    path_abs = os.path.normpath(os.path.abspath(path))
    return path_abs == root_abs or path_abs.startswith(root_abs.rstrip(os.sep) + os.sep)


def check_inside(root: Path, path: Path, what: str = "derived file") -> Path:
    """Refuse `path` unless it lies in `root` (no `..` out of it) and no part of it from `root` down, `root`'s last
    component and `path` included, is a symbolic link. Parts that do not exist yet are fine: they will be made
    as plain folders. Returns `path`."""
    path = Path(path)
    if not lexically_inside(root, path):
        raise InputError(path, f"outside {root}; a {what} stays inside it")
    root_abs = Path(os.path.normpath(os.path.abspath(root)))
    rel = Path(os.path.normpath(os.path.abspath(path))).relative_to(root_abs)
    node = root_abs
    for part in ("", *rel.parts):
        node = node / part if part else node
        if node.is_symlink():
            raise link_error(node)
        if part and not node.exists():
            break
    return path


def refuse_links(root: Path, skip: tuple[Path, ...] = ()) -> None:
    """Walk `root` without following links and refuse the first symbolic link found in it (one line naming it and
    where it points). `skip`: folders under `root` not to walk (a derived folder walked on its own)."""
    root = Path(root)
    if root.is_symlink():
        raise link_error(root)
    skipped = {os.path.normpath(os.path.abspath(p)) for p in skip}
    stack = [root]
    while stack:
        folder = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except FileNotFoundError:
            continue
        except PermissionError:
            raise InputError(folder, "permission denied: odsplat needs to read every folder of the capture") from None
        for entry in entries:
            if entry.is_symlink():
                raise link_error(Path(entry.path))
            if entry.is_dir(follow_symlinks=False) and os.path.normpath(entry.path) not in skipped:
                stack.append(Path(entry.path))


__all__ = ["check_inside", "lexically_inside", "link_error", "refuse_links"]
