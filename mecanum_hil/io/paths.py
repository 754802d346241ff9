"""Whether an output can be written, checked before the work that produces it.

A fit, a training run or a batch of a thousand groups that ends on ``cannot write`` has lost
its time; an output written before a second one fails leaves half a result. The writers create
missing folders, so the check is made where the file will go or in the nearest folder above it
that exists, by making (and removing) a temporary file there: permissions alone say too little
(root, read-only mounts, ``/proc``).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..errors import ConfigError


def check_folder_writable(folder: str | Path, what: str) -> None:
    """One-line :class:`ConfigError` unless a file can be made in ``folder`` (or, when it does
    not exist yet, in its nearest existing parent); nothing is left behind.

    Parameters
    ----------
    folder : str or Path
        Folder the outputs go to.
    what : str
        How the user named it, to start the message (``"--write runs/"``).
    """
    existing = Path(folder).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{what}: {existing} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=existing, prefix=".mecanum-hil-probe-"):
            pass
    except OSError as err:
        raise ConfigError(f"{what}: cannot write in {existing}: {err.strerror or err}") from None


def check_file_writable(path: str | Path, what: str) -> None:
    """One-line :class:`ConfigError` unless ``path`` can be written: not a folder; a file,
    device or pipe there that may be written, or else a folder where a file can be made
    (:func:`check_folder_writable`)."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{what}: a folder is there, not a file")
    if p.exists() and (not p.is_file() or os.access(p, os.W_OK)):
        return  # /dev/null, /dev/stdout, a fifo, >(jq .), a file it may write over
    check_folder_writable(p.absolute().parent, what)
