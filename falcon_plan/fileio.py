"""Writing result files: atomically, readable by others (mode 0644), failing with one clear line.

Every file falcon-plan writes for a user (trajectories, logs, summaries, reports) goes through
:func:`write_text` or :func:`check_writable`: a temporary file in the target folder renamed
into place, so a reader never sees half a file, and an :class:`OutputError` naming the path and
the cause when the folder is missing or not writable.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from falcon_plan.errors import OutputError

FILE_MODE = 0o644
"""Mode of every file written (owner read-write, everyone else read)."""


def check_writable(path: str | os.PathLike[str], what: str = "output") -> Path:
    """Raise :class:`OutputError` unless ``path`` can be created or replaced: its folder exists
    and a file can be created in it (tried: a probe file made and removed), and it is not a
    folder itself. Returns ``path`` as a Path. ``what`` names
    the output in the message (e.g. "plan JSON")."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise OutputError(f"cannot write {what} {path}: it is a folder (give a file name)")
    if not folder.is_dir():
        raise OutputError(f"cannot write {what} {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise OutputError(f"cannot write {what} {path}: permission denied")
    try:  # access() says yes to root everywhere, /proc and read-only mounts included: try it
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        raise OutputError(f"cannot write {what} {path}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(probe)
    return path


def write_bytes(path: str | os.PathLike[str], data: bytes, what: str = "output") -> Path:
    """Write ``data`` to ``path`` atomically with mode 0644; :class:`OutputError` on failure,
    naming the output as ``what``."""
    path = check_writable(path, what)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise OutputError(f"cannot write {what} {path}: {exc.strerror or exc}") from exc
    return path


def write_text(path: str | os.PathLike[str], text: str, what: str = "output") -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically with mode 0644 (see :func:`write_bytes`;
    ``what`` names the output in an error)."""
    return write_bytes(path, text.encode("utf-8"), what)


def make_folder(path: str | os.PathLike[str], what: str = "output folder") -> Path:
    """Create the folder ``path`` (and parents) if needed; :class:`OutputError` naming it as
    ``what`` if impossible."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {what} {path}: {exc.strerror or exc}") from exc
    if not os.access(path, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write into {what} {path}: permission denied")
    return path


@contextmanager
def output_folder(path: str | os.PathLike[str], what: str = "output folder") -> Iterator[Path]:
    """:func:`make_folder` of ``path`` (named ``what`` in errors) for the body of a run:
    should the body fail (any exception, Ctrl-C too), the folders this made are removed again
    if they are still empty, so that a failed run leaves no empty output folder behind."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not p.exists()]  # deepest first
    folder = make_folder(path, what)
    try:
        yield folder
    except BaseException:
        for p in made:
            try:
                p.rmdir()  # only an empty one
            except OSError:
                break
        raise


__all__ = ["FILE_MODE", "OutputError", "check_writable", "make_folder", "output_folder", "write_bytes",
           "write_text"]
