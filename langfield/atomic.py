"""Writing a file so that a reader sees the old file or the whole new one, never half of it.

>>> import tempfile, pathlib
>>> path = pathlib.Path(tempfile.mkdtemp()) / "report.json"
>>> with atomic_path(path) as tmp:
...     _ = tmp.write_text("{}")
>>> path.read_text()
'{}'
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "check_writable_file", "check_writable_folder"]


def check_writable_folder(path: str | Path, what: str = "output") -> Path:
    """Checks, before any work, that ``path`` is or can become a folder.

    Raises:
        NotADirectoryError: ``path``, or a parent of it, is a file.
    """
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise NotADirectoryError(f"{p}: is a file, so the {what} folder {path} cannot be made")
            break
    return path


def check_writable_file(path: str | Path, what: str = "output") -> Path:
    """Checks, before any work, that ``path`` can become a file: not a folder, its folder not a file.

    Raises:
        IsADirectoryError: ``path`` is a folder.
        NotADirectoryError: a parent of ``path`` is a file.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a folder; the {what} is a file")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise NotADirectoryError(f"{parent}: is a file, so {path} cannot be written")
            break
    return path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yields a temporary path beside ``path``; renamed onto ``path`` when the block ends normally,
    removed when it raises. The parent folder is created.

    Raises:
        IsADirectoryError, NotADirectoryError: as :func:`check_writable_file`, before anything is written.
    """
    path = check_writable_file(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
