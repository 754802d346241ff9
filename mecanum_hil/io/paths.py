"""Whether an output can be written, checked before the work that produces it.

A fit, a training run or a batch of a thousand groups that ends on ``cannot write`` has lost
its time; an output written before a second one fails leaves half a result. The writers create
missing folders, so the check is made where the file will go or in the nearest folder above it
that exists, by making (and removing) a temporary file there: permissions alone say too little
(root, read-only mounts, ``/proc``).

An output is also only ever seen whole: :func:`replaced_when_whole` writes a file beside its
place and puts it there when it is complete, :func:`staged_folder` does the same for the files
of a report folder, so Ctrl-C, SIGTERM or an error part-way leaves the previous output as it was
and nothing half-written.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
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


def part_path(path: str | Path) -> Path:
    """Where ``path`` is written before it is whole: ``.NAME.part.EXT`` beside it (the
    extension kept, for writers that choose the format by it)."""
    p = Path(path)
    return p.with_name(f".{p.stem}.part{p.suffix}")


@contextmanager
def replaced_when_whole(path: str | Path) -> Iterator[Path]:
    """Yield the temporary path to write ``path``'s content to; on a normal exit it replaces
    ``path`` in one step, on any way out (an error, Ctrl-C, SIGTERM raised as an exception) it
    is removed and ``path`` stays as it was.

    Parameters
    ----------
    path : str or Path
        The output's final place; its folder must exist. A device or pipe there (``/dev/null``,
        ``>(cmd)``) is written as it is; a symbolic link, where it points (the link stays); a
        file's permissions are kept.
    """
    final = Path(path)
    if final.exists() and not final.is_file():  # /dev/null, /dev/stdout, a fifo: as given
        yield final
        return
    if final.is_symlink():
        final = final.resolve()
    tmp = part_path(final)
    try:
        yield tmp
        if final.exists():
            shutil.copymode(final, tmp)
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


#: A report's staging folder inside its folder: ``.mecanum-hil-PID-XXXX.part``.
_STAGE_PREFIX, _STAGE_SUFFIX = ".mecanum-hil-", ".part"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True  # another user's, or not a pid: not ours to judge
    return True


def _clear_dead_stages(folder: Path) -> None:
    """Remove the staging folders that runs killed where no handler runs (SIGKILL, a power
    cut) left in ``folder``: only this package's, and only those whose process has ended (a
    run writing into the same folder keeps its own)."""
    for stage in folder.glob(f"{_STAGE_PREFIX}*{_STAGE_SUFFIX}"):
        pid = stage.name[len(_STAGE_PREFIX):].split("-", 1)[0]
        if stage.is_dir() and not stage.is_symlink() and pid.isdigit() \
                and not _process_alive(int(pid)):
            shutil.rmtree(stage, ignore_errors=True)


@contextmanager
def staged_folder(out: str | Path, last: Sequence[str] = ()) -> Iterator[Path]:
    """Yield a staging folder inside ``out`` for a report's files; on a normal exit move them
    into ``out`` (those named in ``last``, the report's index, after the others), on any way
    out remove them, leaving an earlier report in ``out`` as it was.

    Parameters
    ----------
    out : str or Path
        The report's folder (created where missing).
    last : sequence of str
        File names moved last, so that a report's index never points at plots of an older run.

    Raises
    ------
    ConfigError
        The folder cannot be made or written, or a folder is in the way of one of the
        report's files (said before any file is moved).

    Notes
    -----
    Files of an earlier report that this one does not write are left in place. The staging
    folder is ``.mecanum-hil-PID-XXXX.part``: two runs into one folder keep theirs apart, and
    a folder of that form whose process has ended (a run killed by SIGKILL) is removed.
    """
    folder = Path(out)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        _clear_dead_stages(folder)
        stage = Path(tempfile.mkdtemp(dir=folder, prefix=f"{_STAGE_PREFIX}{os.getpid()}-",
                                      suffix=_STAGE_SUFFIX))
    except OSError as err:
        raise ConfigError(f"{folder}: cannot write the report there: {err.strerror or err}"
                          ) from None
    try:
        yield stage
        names = sorted(p.name for p in stage.iterdir())
        for name in names:
            there = folder / name
            if there.is_dir() and not there.is_symlink():
                raise ConfigError(f"{there}: a folder is in the way of the report's {name}")
        try:
            for name in [n for n in names if n not in last] + [n for n in names if n in last]:
                os.replace(stage / name, folder / name)
        except OSError as err:
            raise ConfigError(f"{folder}: cannot put the report in place: "
                              f"{err.strerror or err}") from None
        stage.rmdir()
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
