"""``python -m pipeline.accuracy_table``: see :mod:`pipeline.measure.accuracy_table`."""

from __future__ import annotations

from .measure.accuracy_table import main

if __name__ == "__main__":
    raise SystemExit(main())
