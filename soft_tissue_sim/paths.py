"""Where scenes and meshes are found: the source tree, then an installed share/ directory.

Imports nothing of this package, so any module may use it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parent.parent
SCENES_DIR = PACKAGE_ROOT / "config" / "scenes"


def share_dirs() -> list[Path]:
    """Where scenes and meshes may live: the source tree, then an installed share/ directory."""
    dirs = [PACKAGE_ROOT]
    try:  # a colcon / ament install
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("soft_tissue_sim")))
    except Exception:  # noqa: BLE001 - ament index absent or package not installed: source tree only
        pass
    dirs.append(Path(sys.prefix) / "share" / "soft_tissue_sim")  # a plain pip install (setup.py data_files)
    return dirs


def resolve_path(name: str | os.PathLike, base: Path | None = None) -> Path:
    """Find a scene or mesh file: as given, relative to ``base``, then in the package's dirs.

    A name without a suffix (``"default"``, the node's ``scene:=default``) is also tried as
    ``<name>.yaml`` in the scenes directories.
    """
    p = Path(name)
    candidates = [p] if p.is_absolute() else [Path.cwd() / p]
    if base is not None and not p.is_absolute():
        candidates.append(base / p)
    bare = not p.is_absolute() and bool(p.name) and not p.suffix  # a scene's name: "default"
    for d in share_dirs():
        scenes = d / "config" / "scenes"
        candidates += [d / p, scenes / p]
        if bare:
            candidates.append(scenes / p.with_suffix(".yaml"))
        candidates.append(d / "meshes" / p.name)
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise FileNotFoundError(f"cannot find {str(name)!r} (looked in: {', '.join(str(c) for c in candidates)})")
