"""Locating the files shipped with mecanum-hil: robot profiles and calibrations.

A name (``tdam-stm``, ``paper``) is looked up in the project's ``drivers/`` or ``calibration/``
folder; anything that looks like a path is used as it is. In a checkout (or an editable install)
those folders are the repository's own; a wheel carries copies under ``mecanum_hil/_resources``.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError

_PACKAGE_DIR = Path(__file__).resolve().parents[1]
_SEARCH_ROOTS = (_PACKAGE_DIR / "_resources", _PACKAGE_DIR.parent)

DEFAULT_ROBOT = "tdam-stm"
DEFAULT_CALIBRATION = "paper"


#: The folders of a checkout that hold what mecanum-hil ships, beside the package itself.
SHIPPED_FOLDERS = ("bench", "calibration", "docs", "drivers", "examples", "recordings", "tests")


def is_shipped(path: str | Path) -> bool:
    """Whether ``path`` lies in mecanum-hil's own folders: the package (with a wheel's copies
    of the shipped files), or one of :data:`SHIPPED_FOLDERS` of the checkout it runs from."""
    p = Path(path).resolve()
    roots = (_PACKAGE_DIR, *(_PACKAGE_DIR.parent / folder for folder in SHIPPED_FOLDERS))
    return any(p.is_relative_to(root) for root in roots)


def resource_dir(folder: str) -> Path:
    """The shipped folder ``drivers`` or ``calibration``."""
    for root in _SEARCH_ROOTS:
        candidate = root / folder
        if candidate.is_dir():
            return candidate
    raise ConfigError(f"the shipped folder '{folder}/' is missing from this installation")


def resolve(folder: str, name_or_path: str | Path, suffix: str = ".toml") -> Path:
    """A file path for a shipped name or a user path.

    Parameters
    ----------
    folder : str
        ``"drivers"`` or ``"calibration"``.
    name_or_path : str or Path
        A shipped name without suffix, or a path to a file.
    suffix : str
        Suffix of the shipped files.
    """
    p = Path(name_or_path)
    if p.suffix or p.parent != Path(".") or p.exists():
        if not p.exists():
            raise ConfigError(f"{p}: file not found")
        return p
    candidate = resource_dir(folder) / f"{p.name}{suffix}"
    if not candidate.exists():
        available = sorted(f.stem for f in resource_dir(folder).glob(f"*{suffix}"))
        raise ConfigError(
            f"no {folder} file named '{name_or_path}' (shipped: {', '.join(available)})"
        )
    return candidate
