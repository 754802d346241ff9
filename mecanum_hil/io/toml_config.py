"""Reading and checking the project's TOML files, with errors that name the file and key."""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..errors import ConfigError


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file, turning every failure into a :class:`ConfigError` naming the file.
    TOML is UTF-8; a byte-order mark (as some Windows editors save) is accepted."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8-sig")
        return tomllib.loads(text)
    except FileNotFoundError as err:
        raise ConfigError(f"{p}: file not found") from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: not UTF-8 text (byte {err.start})") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from err
    except OSError as err:
        raise ConfigError(f"{p}: cannot read: {err.strerror or err}") from err


class TableReader:
    """Checked access to one table of a TOML document.

    Parameters
    ----------
    table : Mapping
        The parsed table.
    source : str
        File name used in error messages.
    prefix : str
        Dotted path of the table inside the document (``"motor"``, ``"effects.saturation"``).
    """

    def __init__(self, table: Mapping[str, Any], source: str, prefix: str = "") -> None:
        if not isinstance(table, Mapping):
            raise ConfigError(f"{source}: '{prefix}' must be a table")
        self.table = table
        self.source = source
        self.prefix = prefix

    def _key(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def fail(self, key: str, message: str) -> ConfigError:
        """An error naming the file and the dotted key."""
        return ConfigError(f"{self.source}: key '{self._key(key)}' {message}")

    def sub(self, key: str, *, required: bool = True) -> TableReader | None:
        """The sub-table ``key``; ``None`` when absent and not required."""
        if key not in self.table:
            if required:
                raise ConfigError(f"{self.source}: missing table [{self._key(key)}]")
            return None
        return TableReader(self.table[key], self.source, self._key(key))

    def number(
        self,
        key: str,
        default: float | None = None,
        *,
        minimum: float | None = None,
        maximum: float | None = None,
        strict_minimum: bool = False,
    ) -> float:
        """A finite number within bounds; ``default`` when absent (error when no default)."""
        if key not in self.table:
            if default is None:
                raise self.fail(key, "is missing")
            return float(default)
        value = self.table[key]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(key, f"must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(key, f"must be finite, got {value!r}")
        if minimum is not None and (value < minimum or (strict_minimum and value == minimum)):
            relation = ">" if strict_minimum else ">="
            raise self.fail(key, f"must be {relation} {minimum:g}, got {value:g}")
        if maximum is not None and value > maximum:
            raise self.fail(key, f"must be <= {maximum:g}, got {value:g}")
        return value

    def whole_number(self, key: str, default: int | None = None, *,
                     minimum: float | None = None, maximum: float | None = None) -> int:
        """A whole number within bounds (``1.5`` refused; ``2.0`` read as 2); ``default`` when
        absent (error when no default)."""
        value = self.number(key, None if default is None else float(default), minimum=minimum,
                            maximum=maximum)
        if value != int(value):
            raise self.fail(key, f"must be a whole number, got {value:g}")
        return int(value)

    def numbers(self, key: str, length: int, *, minimum: float | None = None) -> tuple[float, ...]:
        """A list of exactly ``length`` finite numbers."""
        if key not in self.table:
            raise self.fail(key, "is missing")
        values = self.table[key]
        if not isinstance(values, list) or len(values) != length:
            raise self.fail(key, f"must be a list of {length} numbers, got {values!r}")
        items = {str(i): v for i, v in enumerate(values)}
        checker = TableReader(items, self.source, self._key(key))
        return tuple(checker.number(str(i), minimum=minimum) for i in range(length))

    def string(self, key: str, default: str | None = None) -> str:
        """A string; ``default`` when absent (error when no default)."""
        if key not in self.table:
            if default is None:
                raise self.fail(key, "is missing")
            return default
        value = self.table[key]
        if not isinstance(value, str):
            raise self.fail(key, f"must be a string, got {value!r}")
        return value

    def reject_unknown(self, known: set[str]) -> None:
        """Fail on keys outside ``known``: a typo must not silently become a default."""
        for key in self.table:
            if key not in known:
                raise self.fail(key, f"is not a known key (known: {', '.join(sorted(known))})")


def toml_value(value: Any) -> str:
    """``value`` (bool, number, string, list) as TOML text; floats round-trip exactly."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        v = float(value)
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if math.isnan(v):
            return "nan"
        return repr(v) if isinstance(value, float) else str(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
        return f'"{escaped}"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def write_toml(path: str | Path, text: str, what: str) -> Path:
    """Write ``text`` to ``path`` (its folder created); ``what`` names it in the error.

    Raises
    ------
    ConfigError
        When the file cannot be written.
    """
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    except OSError as err:
        raise ConfigError(f"{p}: cannot write {what}: {err.strerror or err}") from err
    return p
