"""Keep the garbage collector's full collections off the request path.

A trustlab server holds a few hundred thousand long-lived objects (the web framework, pandas,
plotly, SQLAlchemy's mappers, the protocols and checkpoints). CPython's full (generation 2)
collection walks every one of them: 60–140 ms on the lab machines, during which no request is
served — the slowest answers bench/api.py saw. Freezing what exists once the server has started
moves it to the permanent generation, which collections skip; objects created later are collected
as usual. Thawing at shutdown hands the frozen objects back, so a process that starts and stops
many applications (the tests) frees them like any others.
"""

from __future__ import annotations

import gc


def freeze_startup_objects() -> int:
    """Collect once, then exempt every surviving object from later collections; how many."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def thaw() -> None:
    """Make the frozen objects collectable again (server shutdown)."""
    gc.unfreeze()
