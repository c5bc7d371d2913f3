"""Run lint-imports (the import contracts in pyproject.toml) on this tree's files.

grimp finds `odsplat` with importlib and walks that one folder, but the package is spread over several: setuptools'
package-dir maps odsplat.sync to sync/ and so on, and the editable install resolves those through a meta path
finder that grimp never consults (it would see odsplat/ without its stages). So this lays the package out as it is
installed, odsplat/ with each stage folder as odsplat/<stage>/ (the .py files only), in a temporary folder, puts that
first on PYTHONPATH and runs lint-imports there. Nothing is written into the tree.

Usage: python tools/lint_imports.py [--root TREE] [lint-imports options]; exits with lint-imports' status.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def lay_out(root: Path, dest: Path) -> Path:
    """Copy the package's .py files from `root` into `dest` as installed; returns dest."""
    config = tomllib.loads((root / "pyproject.toml").read_text())
    package_dir = config["tool"]["setuptools"]["package-dir"]
    # Parents first, so that odsplat/ exists before odsplat/sync/ is copied into it.
    for package, folder in sorted(package_dir.items(), key=lambda item: item[0].count(".")):
        target = dest.joinpath(*package.split("."))
        shutil.copytree(root / folder, target, dirs_exist_ok=True,
                        ignore=lambda d, names: [n for n in names
                                                 if not (n.endswith(".py") or (Path(d) / n).is_dir())
                                                 or n == "__pycache__"])
    return dest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=REPO, help="the tree to check (default: this one)")
    args, rest = parser.parse_known_args(argv)
    root = args.root.resolve()
    lint_imports = Path(sys.executable).parent / "lint-imports"
    if not lint_imports.exists():
        lint_imports = Path(shutil.which("lint-imports") or "lint-imports")
    with tempfile.TemporaryDirectory(prefix="odsplat-imports-") as tmp:
        layout = lay_out(root, Path(tmp) / "layout")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(layout), os.environ.get("PYTHONPATH")])))
        cmd = [str(lint_imports), "--no-cache", *rest, str(root / "pyproject.toml")]
        return subprocess.run(cmd, env=env, cwd=tmp).returncode


if __name__ == "__main__":
    sys.exit(main())
