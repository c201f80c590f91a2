"""Reading a TOML file the way editors save them."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

_BOM = "\ufeff"


def load_toml(path: Path) -> dict[str, Any]:
    """Parse ``path`` as UTF-8 TOML, with or without a byte-order mark.

    Windows editors (Notepad) start UTF-8 files with a BOM, which TOML does not allow
    and tomllib reports as "Invalid statement (at line 1, column 1)": it is skipped.
    Raises OSError, UnicodeDecodeError and tomllib.TOMLDecodeError as tomllib.load does.
    """
    text = Path(path).read_bytes().decode("utf-8")
    return tomllib.loads(text.removeprefix(_BOM))
