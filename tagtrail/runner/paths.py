"""Paths the runner writes to: always inside the project's ``outputs/`` or ``artifacts/``.

Dataset names are validated when the pipeline is loaded; this is the second line of defence,
so that no later code path can turn a name into a path outside its folder.
"""

from __future__ import annotations

import re
from pathlib import Path

from tagtrail.errors import SpecError

# ``tempfile.mkstemp``'s names: prefix + 8 random characters.
_TEMP = re.compile(r"^\..+\.[a-z0-9_]{8}$")


def inside(root: Path, *parts: str) -> Path:
    """``root / parts…``, refusing a result that is ``root`` itself or resolves outside it."""
    path = Path(root).joinpath(*parts)
    base = Path(root).resolve()
    target = path.resolve()
    if target == base or base not in target.parents:
        raise SpecError(f"refusing to write {path}: it resolves outside {root} ({target})")
    return path


def clean_temp_files(folder: Path, prefixes: tuple[str, ...] = ("",)) -> list[Path]:
    """Delete the temporary files an atomic write left behind when it was killed (the caller
    holds the store lock, so no writer is using them); returns what was removed."""
    removed = []
    if folder.is_dir():
        for p in folder.iterdir():
            if p.is_file() and _TEMP.match(p.name) and p.name[1:].startswith(prefixes):
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed
