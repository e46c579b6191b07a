"""Writing a file so that a crash, even ``kill -9`` or a power cut, never leaves it half-written.

The data goes to a temporary file in the same directory, is flushed and fsync'ed, then
``os.replace``'d over the target (atomic on POSIX: a reader sees the old file or the new
one, never a mix), then the directory is fsync'ed so the rename itself is on disk
(fsync(2), rename(2)). Every file mazebot saves (maps, runs, pose graphs) goes through here.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def write_atomic(path: str | os.PathLike[str], data: bytes, *, create_folder: bool = True) -> Path:
    """Replace ``path`` with ``data`` atomically, creating its folder unless told not to
    (a file the user named: a folder that is not there is their mistake); returns the path.

    Example::

        write_atomic(run_dir / "map.pgm", encode_pgm(three_state))
    """
    path = Path(path)
    if create_folder:
        path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    with contextlib.suppress(OSError):  # not every file system lets a directory be fsync'ed
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    return path
