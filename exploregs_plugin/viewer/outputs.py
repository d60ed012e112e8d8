"""What a viewer render can show; a leaf module, so the viewer's parts and its config share it
without importing each other."""

from __future__ import annotations

from typing import Literal

OutputKind = Literal["rgb", "depth", "alpha"]
OUTPUT_KINDS: tuple[OutputKind, ...] = ("rgb", "depth", "alpha")
