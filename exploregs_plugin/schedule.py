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
from typing import Literal


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
    coarse_levels: int = 0
    """Coarse-to-fine: training images start downscaled by 2^coarse_levels (0: full size throughout)."""
    coarse_every: int = 1
    """Steps per coarse level: the resolution doubles every this many steps until it is full."""

    def downscale_at(self, step: int) -> int:
        """The factor (a power of 2, 1 = full size) by which step ``step``'s training images are
        downscaled: 2^N for the first ``coarse_every`` steps, then 2^(N-1), ..., then 1."""
        level = max(0, self.coarse_levels - max(step, 0) // max(self.coarse_every, 1))
        return 2 ** level


SHORT_FRACTIONS = {
    "refine_start_frac": 500.0 / 7000.0,
    "refine_stop_frac": 15000.0 / 7000.0,
    "refine_every_frac": 100.0 / 7000.0,
    "reset_every_frac": 3000.0 / 7000.0,
    "sh_degree_interval_frac": 1000.0 / 7000.0,
}
"""The ``short`` schedule: 3DGS's 7k-step result is the first 7000 steps of its 30k run, so its
events at their 3DGS step numbers divided by 7000 (densification from 1/14 of the run to its end,
every 1/70 with the minimum interval, opacity resets at 3/7 and 6/7, the SH degree up every 1/7)."""
SCHEDULE_NAMES = ("3dgs", "short")


@dataclass
class ScheduleConfig:
    """Fractions of the run at which the 3DGS events happen."""

    name: Literal["3dgs", "short"] = "3dgs"
    """3dgs: the 30k-step 3DGS schedule scaled to --max-steps (the fractions below). short: the
    schedule of 3DGS's 7k-step result scaled to --max-steps (it replaces the five fractions below:
    densify from 1/14 of the run to its end, reset opacity every 3/7, SH degree up every 1/7)."""

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
    coarse_levels: int = 0
    """Coarse-to-fine: train on images downscaled by 2^N at the start, the resolution doubling every
    coarse_every_frac of the run until it is full (0: full size throughout). Evaluation is always at
    full size."""
    coarse_every_frac: float = 0.1
    """Coarse-to-fine: each coarse level lasts this fraction of the run (OpenSplat: 3000 of 30k)."""

    def __post_init__(self) -> None:
        if self.name not in SCHEDULE_NAMES:
            raise ValueError(f"schedule name must be one of {', '.join(SCHEDULE_NAMES)}, got {self.name!r}")
        if self.coarse_levels < 0:
            raise ValueError(f"coarse_levels must be >= 0, got {self.coarse_levels}")
        if not 0.0 < self.coarse_every_frac <= 1.0:
            raise ValueError(f"coarse_every_frac must be in (0, 1], got {self.coarse_every_frac}")

    def fractions(self) -> dict[str, float]:
        """The five event fractions of this schedule (the named schedule's, or the fields')."""
        if self.name == "short":
            return dict(SHORT_FRACTIONS)
        return {key: getattr(self, key) for key in SHORT_FRACTIONS}

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

        frac = self.fractions()
        return Schedule(
            max_steps=max_steps,
            refine_start=position(frac["refine_start_frac"] * images),
            refine_stop=position(frac["refine_stop_frac"] * images),
            refine_every=interval(max(self.min_refine_every, int(round(frac["refine_every_frac"] * images)))),
            reset_every=interval(max(self.min_reset_every, int(round(frac["reset_every_frac"] * images)))),
            sh_degree_interval=interval(max(
                self.min_sh_degree_interval, int(round(frac["sh_degree_interval_frac"] * images))
            )),
            views_per_step=views_per_step,
            coarse_levels=self.coarse_levels,
            coarse_every=interval(max(1, int(round(self.coarse_every_frac * images)))),
        )
