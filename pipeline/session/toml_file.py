"""Reading a TOML file the way editors save them."""

from __future__ import annotations

import errno
import stat
import tomllib
from pathlib import Path
from typing import Any

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


def require_regular_file(path: Path) -> None:
    """OSError (``strerror`` "is not a regular file") where ``path`` exists but is not a
    regular file: a directory, a named pipe, a device. A missing path is left to the read."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        raise OSError(errno.EINVAL, "is not a regular file", str(path))
