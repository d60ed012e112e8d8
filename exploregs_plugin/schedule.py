"""Training schedule as fractions of the run, resolved to step numbers.

The 3DGS reference trains 30k steps: densify from step 500 to 15k every 100, reset opacity
every 3k, raise the SH degree every 1k. A short CPU run keeps that *shape*: each event is a
fraction of ``max_steps`` (500/30k = 1/60, 15k/30k = 1/2, 3k/30k = 1/10, 1k/30k = 1/30), with
minimum intervals so that a very short run still has room between events.

With a batch of B views per step (``--batch-size``) the schedule is stated in *images
seen*: a run of ``max_steps`` steps sees ``max_steps x B`` images, every event is resolved
against that count (the minimum intervals too: 3DGS densifies every 100 images), and then
converted to steps by dividing by B. A run at B = 4 with a quarter of the steps densifies,
resets and raises the SH degree after the same numbers of images as the run at B = 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Schedule:
    """Step numbers for one run (all ints, resolved from a :class:`ScheduleConfig`)."""

    max_steps: int
    refine_start: int
    refine_stop: int
    refine_every: int
    reset_every: int
    sh_degree_interval: int
    views_per_step: int = 1
    """Training views rendered per step (the batch size B); the fields above are in steps."""


@dataclass
class ScheduleConfig:
    """Fractions of the run at which the 3DGS events happen."""

    refine_start_frac: float = 1.0 / 60.0
    """Densification starts after this fraction of the run (3DGS: 500 of 30k)."""
    refine_stop_frac: float = 0.5
    """Densification stops after this fraction of the run (3DGS: 15k of 30k)."""
    refine_every_frac: float = 1.0 / 300.0
    """Densification interval as a fraction of the run (3DGS: 100 of 30k)."""
    reset_every_frac: float = 0.1
    """Opacity reset interval as a fraction of the run (3DGS: 3k of 30k)."""
    sh_degree_interval_frac: float = 1.0 / 30.0
    """SH degree is raised every this fraction of the run (3DGS: 1k of 30k)."""
    # Gaussians made by one densification need about as many Adam steps as 3DGS gives them (100)
    # to settle before their gradient is judged again; with fewer, freshly split Gaussians still
    # carry large gradients and the set grows geometrically (measured: 3k -> 71k Gaussians in 300
    # steps with a 10-step interval).
    min_refine_every: int = 100
    """Smallest densification interval in steps (shorter: the Gaussian count runs away)."""
    min_reset_every: int = 200
    """Smallest opacity-reset interval in steps, so Gaussians recover between resets."""
    min_sh_degree_interval: int = 25
    """Smallest interval between SH degree increases."""

    def resolve(self, max_steps: int, views_per_step: int = 1) -> Schedule:
        """Step numbers for a run of ``max_steps`` steps of ``views_per_step`` views each."""
        if max_steps <= 0:
            raise ValueError(f"max_steps must be positive, got {max_steps}")
        if views_per_step <= 0:
            raise ValueError(f"views_per_step must be positive, got {views_per_step}")
        images = max_steps * views_per_step

        def position(n_images: float) -> int:  # the step at which n_images have been seen
            return int(math.floor(n_images)) // views_per_step

        def interval(n_images: int) -> int:
            return max(1, int(round(n_images / views_per_step)))

        return Schedule(
            max_steps=max_steps,
            refine_start=position(self.refine_start_frac * images),
            refine_stop=position(self.refine_stop_frac * images),
            refine_every=interval(max(self.min_refine_every, int(round(self.refine_every_frac * images)))),
            reset_every=interval(max(self.min_reset_every, int(round(self.reset_every_frac * images)))),
            sh_degree_interval=interval(max(
                self.min_sh_degree_interval, int(round(self.sh_degree_interval_frac * images))
            )),
            views_per_step=views_per_step,
        )
