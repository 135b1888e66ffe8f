"""``matoptd --config FILE``: settings from a TOML file, its keys the long flag names.

Only the reading is here; which keys exist, how their values are read and what wins over the
file is ``options.py``'s. A key may be written with dashes or underscores
(``max-jobs-per-user`` or ``max_jobs_per_user``); an unknown key is an error naming the key
and the file, so that a typo never silently falls back to a default.
"""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any, Iterable

try:
    import tomllib
except ImportError:  # Python 3.10: the same parser as a package, if installed
    try:
        import tomli as tomllib
    except ImportError:
        tomllib = None


class ConfigError(ValueError):
    """A config file that cannot be used; the message names the file (and key or line)."""


def load(path: Path, known: Iterable[str]) -> dict[str, Any]:
    """The file's settings by option name (underscores)."""
    known = frozenset(known)
    if tomllib is None:
        raise ConfigError(f"cannot read config file {path}: TOML needs Python 3.11 or newer, "
                          "or 'pip install tomli'")
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f)
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    settings: dict[str, Any] = {}
    for key, value in table.items():
        name = key.replace("-", "_")
        if name not in known:
            near = difflib.get_close_matches(name, known, 1)
            hint = f" (did you mean '{near[0].replace('_', '-')}'?)" if near else ""
            raise ConfigError(f"{path}: unknown key '{key}'{hint}")
        if name in settings:
            raise ConfigError(f"{path}: '{key}' is given twice (dashes and underscores name "
                              "the same key)")
        settings[name] = value
    return settings


def text(value: Any) -> str:
    """A TOML value as the text a flag would have been given: strings and numbers only."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ValueError(f"a {type(value).__name__} where a string or a number belongs")
    return str(value)


def relative(path: Path, config_file: Path) -> Path:
    """A path the file gives, relative to the file's folder: it reads the same from any
    working directory."""
    return path if path.is_absolute() else Path(config_file).parent / path
