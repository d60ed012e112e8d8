"""The rows of many tensors in a new order, in one call where the compiled kernels build: a
densification's new set (:func:`exploregs_plugin.strategies.row_ops.split`) without a gather and a
slice per parameter and Adam moment (docs/training.md, "Operators per step")."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .build import cpp_problem, extension


def gather_rows(tensors: Sequence[Tensor], order: Tensor, zero_from: Sequence[int | None]) -> list[Tensor]:
    """``t.index_select(0, order)`` of every tensor, with the rows from ``zero_from[k]`` on set to
    zero where it is not None (a split's children start with zero Adam moments). On the CPU one
    compiled call copies the rows as bytes: the same values, bit for bit."""
    if order.device.type == "cpu" and cpp_problem() is None and all(t.is_contiguous() and t.dim() > 0 for t in tensors):
        return extension().gather_rows(list(tensors), order, [-1 if z is None else z for z in zero_from])
    out = [t.index_select(0, order) for t in tensors]
    zeroed = [rows[z:] for rows, z in zip(out, zero_from) if z is not None]
    if zeroed:
        torch._foreach_zero_(zeroed)
    return out
