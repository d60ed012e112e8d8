"""Cost estimate of a bench before it starts, from measured seconds per training step.

The rates were measured with ``eg-bench`` runs on the 2-core development machine, one thread
per run (see SECONDS_PER_STEP for the conditions of each). ``farside``, ``nearside`` and
``combined`` have the size of ``default`` (144x108, 28 training views, 3000 points) and use its
rates; the ``-large`` presets are extrapolated by pixel count; dataset paths have no estimate
(the progress lines give one after the first run).
"""

from __future__ import annotations

from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec

SECONDS_PER_STEP: dict[str, dict[str, float]] = {  # per scene, Default's rate first
    "tiny": {"exploregs-default": 0.277, "exploregs-seed": 0.273, "exploregs-split": 0.470},
    "default": {"exploregs-default": 0.106, "exploregs-seed": 0.114, "exploregs-split": 0.116,
                "exploregs-seedsplit": 0.127, "exploregs-ray": 0.101, "exploregs-mcmc": 0.062},
    "dynamic": {"exploregs-4d-default": 0.088, "exploregs-4d-split": 0.122, "exploregs-4d-seedsplit": 0.116},
}
"""Scene -> method -> training seconds per step. ``default``: the mean over the three seeds of
``builtin:combined`` (its size) in the 1000-step ``standard`` bench, run with ``--jobs 2`` (one
thread per run, one run per core) with nothing else on the machine (docs/results.md). ``tiny``:
300-step runs at load 4-11 (docs/bench.md), so an upper bound. ``dynamic``: seed 2 of the
2000-step ``dynamic`` bench, ``--jobs 2``, the machine least shared (docs/results.md). Growth is
included, so a shorter run costs less per step than these."""
SAME_SIZE = {"farside": "default", "nearside": "default", "combined": "default"}
RUN_OVERHEAD_SECONDS = 19.0
"""Per run: process start-up, loading the scene, periodic evaluations, final checkpoint
(quick preset: 452 s wall for 395 s of training in 3 runs)."""


def _reference(name: str) -> tuple[str, float] | None:
    """(measured scene, pixel ratio) for a built-in scene name, or None."""
    from exploregs_plugin.data.builtin.presets import PRESETS

    if name in SECONDS_PER_STEP:
        return name, 1.0
    if name in SAME_SIZE:
        return SAME_SIZE[name], 1.0
    if name in PRESETS:
        p, ref = PRESETS[name], PRESETS["default"]
        return "default", (p.width * p.height) / (ref.width * ref.height)
    return None


def estimate_seconds(spec: BenchSpec, runs: list[tuple[BenchScene, BenchEntry, int]] | None = None,
                     ) -> tuple[float | None, str]:
    """(seconds for ``runs`` (default: the whole bench) with one job, how it was estimated),
    or (None, why not)."""
    if spec.device != "cpu":
        return None, f"the measured rates are CPU rates, and this bench runs on {spec.device}"
    total, assumed, extrapolated, unknown = 0.0, set(), set(), set()
    for scene, entry, _ in spec.runs() if runs is None else runs:
        ref = _reference(scene.data.split(":", 1)[1]) if scene.data.startswith("builtin:") else None
        if ref is None or scene.options:
            unknown.add(scene.name)
            continue
        measured, ratio = ref
        rates = SECONDS_PER_STEP[measured]
        if entry.method not in rates:
            assumed.add(entry.method)
        if ratio != 1.0:
            extrapolated.add(scene.name)
        baseline = next(iter(rates.values()))  # each scene's first rate is its Default's
        total += RUN_OVERHEAD_SECONDS + spec.steps * rates.get(entry.method, baseline) * ratio
    if unknown:
        return None, (f"no measured rate for scene(s) {', '.join(sorted(unknown))}; the progress lines "
                      f"estimate the rest after each run")
    how = "seconds per step of single-threaded runs measured on an otherwise idle 2-core machine; load slows them"
    if assumed:
        how += f"; Default's rate assumed for {', '.join(sorted(assumed))}"
    if extrapolated:
        how += f"; {', '.join(sorted(extrapolated))} extrapolated by pixel count"
    return total, how
