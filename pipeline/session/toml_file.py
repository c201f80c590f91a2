"""Reading a TOML file the way editors save them."""

from __future__ import annotations

import difflib
import errno
import stat
import tomllib
from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import Any

from ..errors import PipelineError

_BOM = "\ufeff"


def load_toml(path: Path) -> dict[str, Any]:
    """Parse ``path`` as UTF-8 TOML, with or without a byte-order mark.

    Windows editors (Notepad) start UTF-8 files with a BOM, which TOML does not allow
    and tomllib reports as "Invalid statement (at line 1, column 1)": it is skipped.
    Raises OSError, UnicodeDecodeError and tomllib.TOMLDecodeError as tomllib.load does;
    OSError also for a path that is not a regular file (a named pipe would block the read
    until something writes to it), TOMLDecodeError for arrays or tables nested too deeply
    to parse.
    """
    require_regular_file(Path(path))
    text = Path(path).read_bytes().decode("utf-8")
    try:
        return tomllib.loads(text.removeprefix(_BOM))
    except RecursionError:
        raise tomllib.TOMLDecodeError("arrays or tables nested too deeply") from None


def read_toml(path: Path, *, error: type[PipelineError]) -> dict[str, Any]:
    """:func:`load_toml`, its failures raised as ``error`` naming ``path`` and what to do
    (a missing file raises FileNotFoundError, for the caller to name in its own terms)."""
    try:
        return load_toml(path)
    except FileNotFoundError:
        raise
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: TOML syntax error: {exc}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: is not UTF-8 text; save it as UTF-8") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror}") from None


def require_regular_file(path: Path) -> None:
    """OSError (``strerror`` "is not a regular file") where ``path`` exists but is not a
    regular file: a directory, a named pipe, a device. A missing path is left to the read."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        raise OSError(errno.EINVAL, "is not a regular file", str(path))


def check_keys(
    data: Mapping[str, Any],
    allowed: Collection[str],
    source: str,
    *,
    error: type[PipelineError],
    where: str = "",
    hint: Callable[[str], str] | None = None,
) -> None:
    """Raise ``error`` on the first key of ``data`` that is not in ``allowed``.

    The message names ``source`` and the key (after ``where``, e.g. "[workspace] "), then
    ``hint(key)`` (where the key belongs, " (...)") or, when that is empty, the allowed name
    nearest its spelling, then every allowed name: a misspelt key must not fall back to a
    default without a word.
    """
    for key in data:
        if key not in allowed:
            found = (hint(key) if hint is not None else "") or nearest_name(key, allowed)
            raise error(f"{source}: unknown key {where}{key!r}{found}; allowed: {', '.join(sorted(allowed))}")


def nearest_name(key: str, allowed: Collection[str]) -> str:
    """`` (did you mean 'NAME'?)`` for the name of ``allowed`` nearest ``key``'s spelling, else ""."""
    nearest = difflib.get_close_matches(key, sorted(allowed), n=1)
    return f" (did you mean {nearest[0]!r}?)" if nearest else ""
