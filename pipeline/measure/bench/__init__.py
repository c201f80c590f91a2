"""``make bench``: speed, side by side with the original algorithm.

``run`` orchestrates; ``stages`` times the per-frame stages and carving methods in
process; ``e2e`` times whole ``process`` runs as subprocesses; ``timing`` holds the
statistics; ``report`` the targets, table and JSON; ``chart`` the PNG.
"""

from __future__ import annotations

from .run import main, run_bench

__all__ = ["main", "run_bench"]
