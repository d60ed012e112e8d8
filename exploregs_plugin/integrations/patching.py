"""Setting another package's attribute for the length of a block: the one way the integrations
change gsplat's, tyro's or a strategy's behaviour without editing their code."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any


@contextlib.contextmanager
def attribute_set_to(owner: Any, name: str, value: Any) -> Iterator[None]:
    """``owner.name = value`` inside the block, the old value restored after it (also on error)."""
    saved = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, saved)
