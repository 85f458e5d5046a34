"""Writing files so that an interrupted write never destroys the previous version."""

from __future__ import annotations

import contextlib
import io
import os
import pathlib
import tempfile
from typing import Iterator, Union

PathOrFile = Union[str, pathlib.Path, io.BufferedIOBase]


def with_suffix(path: Union[str, pathlib.Path], suffix: str) -> pathlib.Path:
    """``path`` as SB3 writes it: with ``.suffix`` added when it has none (and ``suffix`` is not empty)."""
    path = pathlib.Path(path)
    return pathlib.Path(f"{path}.{suffix}") if path.suffix == "" and suffix else path


def _mode_of_new_files() -> int:
    """The permissions ``open`` gives a new file: 0666 less the process's umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_target(path: PathOrFile, suffix: str) -> Iterator[PathOrFile]:
    """Where to write ``path``: a temporary file in its folder, renamed over ``path`` (with SB3's
    ``suffix`` rule, :func:`with_suffix`) once the block succeeds, and removed if it fails. The
    rename is atomic on one filesystem, so readers see the old file or the new one, never half of
    one. A file object is written as given."""
    if not isinstance(path, (str, pathlib.Path)):
        yield path
        return
    final = with_suffix(path, suffix)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=f".partial.{suffix}", dir=final.parent)
    os.close(fd)
    os.chmod(tmp, _mode_of_new_files())  # mkstemp's 0600 would hide the file from other users
    try:
        yield pathlib.Path(tmp)
        os.replace(tmp, final)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
