"""Consistent copies of the Gaussian parameters for the render thread.

Training changes the parameters in place (optimizer steps) and replaces them (densification
changes the row count of every tensor at once). The render thread must therefore never read
the live tensors: the training thread copies them at a step boundary, where all tensors hold
the same step and the same rows, and publishes the copy. Copies are made only when the render
thread has asked for one, so training pays for a copy at most once per rendered frame.
"""

from __future__ import annotations

import copy
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor


class SnapshotError(ValueError):
    """The parameters handed to the viewer are not a consistent Gaussian set."""


@dataclass(frozen=True)
class Snapshot:
    """Detached copies of the raw Gaussian parameters at one training step.

    params: ``means [N, 3]``, ``scales [N, 3]``, ``quats [N, 4]``, ``opacities [N]``,
    ``sh0 [N, 1, 3]``, ``shN [N, K-1, 3]`` (the parameter contract's names).
    """

    params: dict[str, Tensor]
    step: int
    version: int
    field: Any = None
    """A dynamic scene's deformation field (a copy on the host), None for a static one."""

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])


REQUIRED_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def copy_params(params: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Detached clones of the Gaussian parameters; checks that every tensor has the same rows."""
    missing = [k for k in REQUIRED_KEYS if k not in params]
    if missing:
        raise SnapshotError(f"viewer parameters lack {missing}; need {list(REQUIRED_KEYS)}")
    with torch.no_grad():
        out = {k: params[k].detach().to("cpu", copy=True) for k in REQUIRED_KEYS}
    rows = {k: int(v.shape[0]) for k, v in out.items()}
    if len(set(rows.values())) != 1:
        raise SnapshotError(f"viewer parameters disagree on the number of Gaussians: {rows}")
    return out


class SnapshotStore:
    """Hand-over point between the training thread (``offer``) and the render thread
    (``request`` / ``latest``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latest: Snapshot | None = None
        self._requested = True  # the first offer always publishes
        self._version = 0
        self.copies = 0
        """Number of copies made (each one cost the training thread one clone of the set)."""

    def request(self) -> None:
        """Ask the training thread for a newer snapshot at its next step boundary."""
        with self._lock:
            self._requested = True

    @property
    def requested(self) -> bool:
        with self._lock:
            return self._requested

    def offer(self, params: Mapping[str, Tensor], step: int, force: bool = False, field: Any = None) -> bool:
        """Called by the thread that owns ``params`` at a step boundary. Copies and publishes
        them (and a dynamic scene's deformation ``field``) when a snapshot was requested and
        ``step`` differs from the published one's (or ``force``); returns whether it did."""
        with self._lock:
            if not force and not self._requested:
                return False
            if not force and self._latest is not None and self._latest.step == int(step):
                # Nothing trained since the last copy (e.g. while paused): keep it.
                self._requested = False
                return False
        # The copy is made outside the lock: the caller owns the tensors, and the render
        # thread only ever reads published copies, so it never waits for a copy to finish.
        copied = copy_params(params)
        field_copy = None
        if field is not None:
            with torch.no_grad():
                field_copy = copy.deepcopy(field).to("cpu").requires_grad_(False)
        with self._lock:
            self._version += 1
            self._latest = Snapshot(copied, int(step), self._version, field_copy)
            self._requested = False
            self.copies += 1
        return True

    def latest(self) -> Snapshot | None:
        with self._lock:
            return self._latest
