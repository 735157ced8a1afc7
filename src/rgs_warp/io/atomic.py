"""Atomic file writes: a reader (or a run resumed after a crash) sees the old file or the whole new
one, never a half-written one.

The new content goes to a temporary file in the target's folder (same file system, so the rename is
atomic), is flushed and fsync'ed, then ``os.replace``s the target; the folder is fsync'ed so the
rename itself survives a power cut.  On any error the temporary file is removed and the target is
left as it was.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO


class SaveError(OSError):
    """Some files of a folder could not be written; the others were (``saved``).  The message names
    the folder, each failed file with its error, and what was saved."""

    def __init__(self, folder: str | Path, saved: list[str], failed: dict[str, BaseException]):
        self.folder, self.saved, self.failed = Path(folder), list(saved), dict(failed)
        errors = "; ".join(f"{name}: {_reason(e)}" for name, e in failed.items())
        super().__init__(f"{folder}: could not write {errors}; saved: {', '.join(saved) or 'nothing'}")


def _reason(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror:  # without the file name: the message names the file
        return f"[Errno {e.errno}] {e.strerror}" if e.errno else e.strerror
    return f"{type(e).__name__}: {e}"


@contextmanager
def atomic_write(path: str | Path, text: bool = False) -> Iterator[IO]:
    """``with atomic_write(path) as f: f.write(...)``: ``f`` is a binary file (``text=True``: UTF-8
    text) that replaces ``path`` when the block ends without an exception."""
    path = Path(path)
    # opened with "x" rather than through mkstemp, so the file gets the umask's permissions as a
    # plain open would (mkstemp's are 0600)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "x" if text else "xb", **({"encoding": "utf-8"} if text else {})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(path.parent)


def write_text_atomic(path: str | Path, text: str) -> None:
    """``Path.write_text`` (UTF-8), atomically."""
    with atomic_write(path, text=True) as f:
        f.write(text)


def fsync_dir(folder: str | Path) -> None:
    """Make the entries of ``folder`` (a rename into it) durable; a no-op where folders cannot be
    opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
