"""Named bench entries (the methods and the controls) and the presets quick / standard / real /
full / real-gpu / dynamic / dnerf and the ablations."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec, BenchSpecError, check_name

LOWTHRESH_GROW_GRAD2D = 0.0001
"""Gradient threshold of the ``default-lowthresh`` control (Default: 0.0002), from a sweep of
``--strategy.grow-grad2d`` on ``builtin:combined`` at the standard budget (1000 steps,
docs/bench.md): 1e-4 gives 16305 Gaussians, between Split's 13634 and Seed+Split's 18545 there
(seed 0), so a gain of exploration over it is not a gain of count."""


DYNAMIC_LOWTHRESH_GROW_GRAD2D = 6e-05
"""Gradient threshold of the ``4d-default-lowthresh`` control on ``builtin:dynamic`` (Default:
0.0002), from a sweep at 2000 steps, seed 0 (docs/results.md): 1.4e-4, 1.2e-4, 8e-5 and 6e-5 give
17 904, 18 634, 21 301 and 23 025 Gaussians, against 25 085 for 4d-split; the lowest comes closest,
so a gain of exploration over it is not a gain of count."""


DYNAMIC_ENTRIES = (
    BenchEntry("4d-default", "exploregs-4d-default", (), "4DGS with 3DGS density control (the baseline)"),
    BenchEntry("4d-split", "exploregs-4d-split", (), "4DGS + Random Splitting (5 per step)"),
    BenchEntry("4d-seedsplit", "exploregs-4d-seedsplit", (), "4DGS + Random Seeding + Random Splitting"),
    BenchEntry("4d-default-lowthresh", "exploregs-4d-default",
               ("--strategy.grow-grad2d", repr(DYNAMIC_LOWTHRESH_GROW_GRAD2D)),
               "control: 4d-default with a lower gradient threshold, near 4d-split's count"),
)
"""The dynamic bench's entries (also named entries for --methods)."""


AUTO_CAP = ("--strategy.cap-max", "auto")
"""MCMC's automatic cap: growth stops when the training loss stops falling (docs/strategies.md)."""


def relaxed_prune_scale3d() -> float:
    """The world-size prune threshold Seeding uses while it seeds (x extent), read from the
    strategy so the control follows any change of Seeding's default."""
    from exploregs_plugin.strategies import SeedingStrategy

    return float(SeedingStrategy().seeding.prune_scale3d)


def named_entries() -> dict[str, BenchEntry]:
    """Entries known by a short name; any registered method name is an entry too."""
    entries = [
        BenchEntry("default", "exploregs-default", (), "3DGS adaptive density control (the baseline)"),
        BenchEntry("default-relaxed-prune", "exploregs-default",
                   ("--strategy.prune-scale3d", repr(relaxed_prune_scale3d())),
                   "control: Default with the relaxed world-size prune that Seeding uses while seeding"),
        BenchEntry("default-lowthresh", "exploregs-default",
                   ("--strategy.grow-grad2d", repr(LOWTHRESH_GROW_GRAD2D)),
                   "control: Default with a lower gradient threshold, as many Gaussians as Split or more"),
        BenchEntry("seed", "exploregs-seed", (), "Random Seeding"),
        BenchEntry("split", "exploregs-split", (), "Random Splitting"),
        BenchEntry("seedsplit", "exploregs-seedsplit", (), "Random Seeding + Random Splitting"),
        BenchEntry("ray", "exploregs-ray", (), "Default + ray-constrained position noise"),
        BenchEntry("mcmc", "exploregs-mcmc", (), "3DGS-MCMC"),
        BenchEntry("mcmc-ray", "exploregs-mcmc-ray", (), "3DGS-MCMC with ray-only noise"),
        BenchEntry("mcmc-auto", "exploregs-mcmc", AUTO_CAP, "3DGS-MCMC with the count chosen by the training loss"),
        BenchEntry("mcmc-explore", "exploregs-mcmc-explore", (),
                   "3DGS-MCMC whose relocation and growth explore (size-weighted random splits)"),
        BenchEntry("mcmc-explore-auto", "exploregs-mcmc-explore", AUTO_CAP,
                   "MCMC-explore with the count chosen by the training loss"),
        BenchEntry("guided", "exploregs-guided", (), "guided seeding: seeds on the rays of the highest-error pixels"),
        BenchEntry("occlusion", "exploregs-occlusion", (), "occlusion-aware splitting"),
        BenchEntry("guided-occlusion", "exploregs-guided-occlusion", (), "guided seeding + occlusion-aware splitting"),
        *DYNAMIC_ENTRIES,
    ]
    return {e.name: e for e in entries}


def entry_from_arg(text: str) -> BenchEntry:
    """``seed`` (a named entry), ``exploregs-seed`` (a registered method) or ``NAME=METHOD``
    (a new row that runs METHOD, usually given overrides with ``--override NAME:ARGS``)."""
    from exploregs_plugin.method_configs import all_methods

    name, sep, method = text.partition("=")
    named = named_entries()
    if sep:
        target = named.get(method)
        if target is not None:  # NAME=seed: a copy of a named entry under another name
            return BenchEntry(check_name("entry", name), target.method, target.overrides, target.description)
        if method not in all_methods():
            raise BenchSpecError(f"entry {text!r}: unknown method {method!r}; named entries: "
                                 f"{', '.join(named)}; methods: {', '.join(sorted(all_methods()))}")
        return BenchEntry(check_name("entry", name), method)
    if text in named:
        return named[text]
    methods = all_methods()
    if text in methods:
        return BenchEntry(check_name("entry", text), text, (), methods[text].description)
    raise BenchSpecError(f"unknown entry {text!r}; named entries: {', '.join(named)}; "
                         f"methods: {', '.join(sorted(methods))}; or NAME=METHOD")


def shared_scenes_root() -> Path:
    """``../shared/scenes`` next to the repository (the real captured scenes, when present)."""
    return Path(__file__).resolve().parents[2].parent / "shared" / "scenes"


QUICK_ENTRIES = ("default", "seed", "split")
QUICK_STEPS = 300
STANDARD_ENTRIES = ("default", "default-relaxed-prune", "seed", "split", "seedsplit", "ray", "mcmc")
STANDARD_SCENES = ("farside", "nearside", "combined")
STANDARD_STEPS = 1000
STANDARD_SEEDS = (0, 1, 2)
REAL_SCENES = {"beer": ("beer", 8), "fox": ("fox", 12)}
"""name -> (folder in ../shared/scenes, data factor): beer 720x1280 -> 90x160, fox 1080x1920 -> 90x160."""
REAL_STEPS = 600
REAL_GPU_SCENES = {"beer": ("beer", 1), "fox": ("fox", 2)}
"""name -> (folder, data factor) at the paper's scale: beer at its full 720x1280, fox at 540x960
(the usual factor 2 of a 1080p capture)."""
REAL_GPU_STEPS = 30_000
REAL_GPU_SEEDS = (0, 1, 2)
PAPER_BUDGET = ("--strategy.budget", "paper")
"""The paper's absolute exploration budget (20 seeds per densification, 20 random splits per step),
made for 30k steps and 1-3M Gaussians."""
ANALYSIS_STEPS = 600
ANALYSIS_BASELINES = {"branch-ablation": "all-branches", "split-ablation": "default-grad0.0002"}
"""Entry each ablation's paired differences are taken against (the unablated configuration)."""


def _entries(names: tuple[str, ...]) -> tuple[BenchEntry, ...]:
    named = named_entries()
    return tuple(named[n] for n in names)


def quick() -> BenchSpec:
    """A few minutes: the tiny scene (64x48), Default / Seed / Split, one seed, 300 steps (the
    shortest run whose schedule densifies and seeds: one step, step 100)."""
    return BenchSpec(entries=_entries(QUICK_ENTRIES), scenes=(BenchScene("tiny", "builtin:tiny"),),
                     seeds=(0,), steps=QUICK_STEPS, eval_count=4, name="quick")


def standard() -> BenchSpec:
    """The built-in Blur-Trap scenes x the paper's comparison and the relaxed-prune control x 3 seeds."""
    return BenchSpec(entries=_entries(STANDARD_ENTRIES),
                     scenes=tuple(BenchScene(n, f"builtin:{n}") for n in STANDARD_SCENES),
                     seeds=STANDARD_SEEDS, steps=STANDARD_STEPS, eval_count=5, name="standard")


def real(root: Path | None = None) -> BenchSpec:
    """The captured scenes in ``../shared/scenes`` at reduced resolution; absent ones are skipped
    with a note (BenchSpecError when none is present)."""
    scenes, notes = _captured_scenes("real", REAL_SCENES, root)
    return BenchSpec(entries=_entries(("default", "seed", "split", "seedsplit")), scenes=scenes,
                     seeds=(0,), steps=REAL_STEPS, eval_count=4, name="real", notes=notes)


def _captured_scenes(preset: str, table: dict[str, tuple[str, int]], root: Path | None
                     ) -> tuple[tuple[BenchScene, ...], tuple[str, ...]]:
    """The scenes of ``table`` (name -> (folder, data factor)) found under ``root`` (default
    ../shared/scenes), and a note for each absent one; BenchSpecError when none is there."""
    root = Path(root) if root is not None else shared_scenes_root()
    scenes = tuple(BenchScene(name, str(root / folder), ("--data-factor", str(factor)))
                   for name, (folder, factor) in table.items() if (root / folder).is_dir())
    notes = tuple(f"{preset} preset: {root / folder} is absent; scene {name!r} skipped"
                  for name, (folder, _) in table.items() if not (root / folder).is_dir())
    if not scenes:
        raise BenchSpecError(f"{preset} preset: no captured scenes under {root} (expected "
                             f"{', '.join(table)}); nothing to run")
    return scenes, notes


def real_gpu(root: Path | None = None) -> BenchSpec:
    """The paper's recipe on the captured scenes, on a GPU: 30k steps with the 3DGS schedule
    unscaled (densify from 500 to 15k every 100, opacity reset every 3k, SH degree up by one
    every 1k to 3), full or the usual resolution, every 8th view for testing, the paper's
    exploration budget, three seeds. MCMC is capped at Default's final count, and the
    low-threshold control at Seed+Split's, so counts match (``{ENTRY:num_gaussians}``)."""
    scenes, notes = _captured_scenes("real-gpu", REAL_GPU_SCENES, root)
    named = named_entries()
    entries = (
        named["default"],
        named["default-relaxed-prune"],
        BenchEntry("default-lowthresh", "exploregs-default",
                   named["default-lowthresh"].overrides + ("--strategy.cap-max", "{seedsplit:num_gaussians}"),
                   "control: Default with the lower gradient threshold, capped at Seed+Split's final count"),
        BenchEntry("seed", "exploregs-seed", PAPER_BUDGET, "Random Seeding, the paper's budget"),
        BenchEntry("split", "exploregs-split", PAPER_BUDGET, "Random Splitting, the paper's budget"),
        BenchEntry("seedsplit", "exploregs-seedsplit", PAPER_BUDGET, "Random Seeding + Splitting, the paper's budget"),
        BenchEntry("mcmc", "exploregs-mcmc", ("--strategy.cap-max", "{default:num_gaussians}"),
                   "3DGS-MCMC capped at Default's final count"),
    )
    return BenchSpec(entries=entries, scenes=scenes, seeds=REAL_GPU_SEEDS, steps=REAL_GPU_STEPS,
                     eval_count=6, name="real-gpu", notes=notes)


FULL_SCENES = {"beer": ("beer", 6), "fox": ("fox", 9)}
"""name -> (folder in ../shared/scenes, data factor) of the full-schedule CPU bench: beer 720x1280
-> 120x213, fox 1080x1920 -> 120x213, both 120 pixels high (see FULL_GROW_GRAD2D). Chosen by
measurement (docs/results.md, "Full schedule on a CPU")."""
FULL_HEIGHT = 120
"""Image height of both scenes at their factor (the densification threshold depends on it)."""
REFERENCE_HEIGHT = 720
"""Image height at which the full bench's Default uses 3DGS's own threshold (beer's capture)."""
FULL_GROW_GRAD2D = round(0.0002 * REFERENCE_HEIGHT / FULL_HEIGHT, 8)
"""Default's densification threshold in the full bench: 3DGS's 0.0002 x 720 / 120. The statistic
is a view-averaged NDC gradient, and for a Gaussian of about a pixel it scales as 1 / H (the loss
is a mean over the image's pixels, the NDC factor is W / 2 and H / 2): at a sixth of the height
the same errors give six times the gradient. With 0.0002 itself, Default on beer at 120 or 60
pixels high grew from 4.4k to about 100k Gaussians by step 3000 of 30k and kept growing (far past
a CPU's budget and any sensible count for so few pixels); at 0.0012, on beer at 120 pixels high,
it had 9.5k at step 3000, 6.8k after the prune that follows the first opacity reset and 8.0k at
step 5000 (docs/results.md). Every Default-family entry uses it, the count control half of it."""
FULL_STEPS = 30_000
FULL_SEEDS = (0, 1, 2)
FULL_BUDGET = "cpu-small"
"""Exploration budget of the full bench: the paper's ratios of explored to final Gaussians (0.19
random splits and 0.2% seeds per final Gaussian) for about 20k final Gaussians, which over the 30k
schedule resolves to 3 random splits every 11 steps and 2 seeds every 700. The paper's absolute
budget (20 splits every step, 20 seeds per densification), made for 1.5M Gaussians, does not fit a
CPU: Seed+Split with it on beer at 120 pixels high had 60k Gaussians at step 3300 (Default: 7k)
and ran at 5 steps per second and falling, hours for one run."""
OFFICIAL_BUDGET = ("--strategy.budget", FULL_BUDGET, "--strategy.seeding.n-seed", "10",
                   "--strategy.seeding.every", "700", "--strategy.split-scale-factor", "1.6",
                   "--strategy.seeding.box-mode", "cameras", "--strategy.seeding.prune-scale3d", "10.0")
"""The paper's released code, where it differs from its text, at the full bench's scale: five
times the seeds (the code: 100 every 100 steps against the text's 20 per densification, here 10
every 700 against 2), seeds in the cube of the camera extent (the text: the box of the
Gaussians), children at scale / (0.8 N) with N = 2 and the 10x-extent world-size prune while
seeding (both as the text), the same random splits. Seeding and splitting stop with
densification (15k of 30k)."""


def full(root: Path | None = None) -> BenchSpec:
    """The paper's claims at the standard 3DGS schedule on the captured scenes, on a CPU: 30k
    steps (densify from 500 to 15k every 100, opacity reset every 3k, SH degree up every 1k),
    every 8th view for testing, at the data factor of :data:`FULL_SCENES` and the densification
    threshold of :data:`FULL_GROW_GRAD2D`. Default and Seed+Split with three seeds, the other
    methods and the controls with one; the exploration methods at the paper's ratios
    (:data:`FULL_BUDGET`) and Seed+Split also with its released code's settings
    (``seedsplit-official``).
    MCMC and MCMC-ray are capped at Default's final count and the low-threshold control at
    Seed+Split's, so counts match. Meant for ``--jobs 2`` with one thread per run."""
    scenes, notes = _captured_scenes("full", FULL_SCENES, root)
    named, once = named_entries(), (0,)
    grad = ("--strategy.grow-grad2d", repr(FULL_GROW_GRAD2D))
    budget = ("--strategy.budget", FULL_BUDGET)
    entries = (
        BenchEntry("default", "exploregs-default", grad, "3DGS adaptive density control (the baseline)"),
        BenchEntry("seedsplit", "exploregs-seedsplit", budget + grad, "Random Seeding + Splitting"),
        BenchEntry("seed", "exploregs-seed", budget + grad, "Random Seeding", seeds=once),
        BenchEntry("split", "exploregs-split", budget + grad, "Random Splitting", seeds=once),
        BenchEntry("seedsplit-official", "exploregs-seedsplit", OFFICIAL_BUDGET + grad,
                   "Random Seeding + Splitting with the released code's settings", seeds=once),
        replace(named["default-relaxed-prune"], overrides=named["default-relaxed-prune"].overrides + grad,
                seeds=once),
        BenchEntry("mcmc", "exploregs-mcmc", ("--strategy.cap-max", "{default:num_gaussians}"),
                   "3DGS-MCMC capped at Default's final count", seeds=once),
        BenchEntry("mcmc-ray", "exploregs-mcmc-ray", ("--strategy.cap-max", "{default:num_gaussians}"),
                   "3DGS-MCMC with ray-only noise, capped at Default's final count", seeds=once),
        BenchEntry("default-lowthresh", "exploregs-default",
                   ("--strategy.grow-grad2d", repr(round(FULL_GROW_GRAD2D / 2, 8)),
                    "--strategy.cap-max", "{seedsplit:num_gaussians}"),
                   "control: Default at half the threshold, capped at Seed+Split's final count", seeds=once),
    )
    return BenchSpec(entries=entries, scenes=scenes, seeds=FULL_SEEDS, steps=FULL_STEPS,
                     eval_count=10, name="full", notes=notes)


TTQ_SCENES = {"beer": ("beer", 4), "fox": ("fox", 4)}
"""name -> (folder, data factor) of the time-to-quality bench: beer 720x1280 -> 180x320 (the issue's
24 dB target), fox 1080x1920 -> 270x480."""
TTQ_STEPS = 1000
"""Steps of the captured scenes' runs (beer reached 24.0 dB by step 800 of 1000 in the issue); the
built-in scene trains the README's 1500 (TTQ_BUILTIN_STEPS)."""
TTQ_BUILTIN_STEPS = 1500
TTQ_EVAL_COUNT = 20
"""Test evaluations per run: the points at which the time to a PSNR is read (every 50 steps at 1000)."""
TTQ_ENTRIES = (
    BenchEntry("default", "exploregs-default", (), "today's default (the baseline of the ratios)"),
    BenchEntry("c2f", "exploregs-default", ("--schedule.coarse-levels", "2"),
               "coarse-to-fine: images at 1/4, then 1/2, each for a tenth of the run, then full size"),
    BenchEntry("short", "exploregs-default", ("--schedule.name", "short"),
               "the short schedule (3DGS's 7k-step result scaled to the run)"),
    BenchEntry("c2f-short", "exploregs-default", ("--schedule.coarse-levels", "2", "--schedule.name", "short"),
               "both"),
    BenchEntry("seedsplit", "exploregs-seedsplit", (), "Random Seeding + Splitting, the README's main method"),
    BenchEntry("seedsplit-c2f", "exploregs-seedsplit", ("--schedule.coarse-levels", "2"),
               "Random Seeding + Splitting, coarse-to-fine"),
)


def time_to_quality(root: Path | None = None) -> BenchSpec:
    """Training seconds to given test PSNRs (``bench/time_quality.py``): Default, coarse-to-fine,
    the short schedule and both, and Seed+Split without and with coarse-to-fine, on beer and fox at --data-factor 4 and on builtin:default, with
    frequent evaluations (their time is not in the training clock)."""
    scenes, notes = _captured_scenes("time-to-quality", TTQ_SCENES, root)
    scenes = scenes + (BenchScene("default", "builtin:default", ("--max-steps", str(TTQ_BUILTIN_STEPS))),)
    return BenchSpec(entries=TTQ_ENTRIES, scenes=scenes, seeds=(0,), steps=TTQ_STEPS,
                     eval_count=TTQ_EVAL_COUNT, name="time-to-quality", notes=notes)


def full_explore(root: Path | None = None) -> BenchSpec:
    """Issue 49's matrix: exploration inside MCMC's budget at the full schedule, with ``full``'s
    recipe (scenes, steps, seeds, evaluations). MCMC and MCMC-explore capped at Default's final
    count, three seeds each (Default too: it sets their count per seed); MCMC-explore with the
    automatic cap, guided + occlusion-aware exploration and, for reference, Seed+Split and the
    relaxed-prune control, one seed each (``full`` measured Seed+Split's seed spread). The entries
    it shares with ``full`` have ``full``'s settings, so in ``full``'s output folder their finished
    runs are reused."""
    spec = full(root)
    named, once = named_entries(), (0,)
    reused = {e.name: e for e in spec.entries}
    count = ("--strategy.cap-max", "{default:num_gaussians}")
    grad = ("--strategy.grow-grad2d", repr(FULL_GROW_GRAD2D))
    entries = (
        reused["default"],
        replace(reused["mcmc"], seeds=None),
        BenchEntry("mcmc-explore", "exploregs-mcmc-explore", count,
                   "3DGS-MCMC whose relocation and growth explore, capped at Default's final count"),
        replace(named["mcmc-explore-auto"], seeds=once),
        BenchEntry("guided-occlusion", "exploregs-guided-occlusion", ("--strategy.budget", FULL_BUDGET) + grad,
                   "guided seeding + occlusion-aware splitting", seeds=once),
        replace(reused["seedsplit"], seeds=once),
        reused["default-relaxed-prune"],
    )
    return replace(spec, entries=entries, name="full-explore")


CAP_SWEEP_FACTORS = (0.125, 0.25, 0.5, 2.0)
"""Fixed caps of the cap sweep, as multiples of Default's final count (1 is full-explore's own
``mcmc-explore`` entry). 1/8 was added after beer's sweep ended best at its smallest cap (1/4),
below which the sweep's best could lie."""


def cap_sweep(root: Path | None = None) -> BenchSpec:
    """Issue 49's check of ``cap_max auto``: MCMC-explore at fixed caps of 1/8, 1/4, 1/2, 1 and 2 times
    Default's final count, and with the automatic cap, on beer and fox with ``full``'s recipe, seed
    0. The automatic count should land within 25% of the smallest fixed cap whose PSNR is within
    0.1 dB of the sweep's best. Default, ``mcmc-explore`` and ``mcmc-explore-auto`` are
    full-explore's entries: in its output folder their runs are reused."""
    spec = full_explore(root)
    shared = {e.name: e for e in spec.entries}
    swept = {f: BenchEntry(f"mcmc-explore-x{f:g}", "exploregs-mcmc-explore",
                           ("--strategy.cap-max", f"{{default:num_gaussians*{f:g}}}"),
                           f"MCMC-explore capped at {f:g} x Default's final count")
             for f in CAP_SWEEP_FACTORS}
    entries = (shared["default"], swept[0.125], swept[0.25], swept[0.5], shared["mcmc-explore"], swept[2.0],
               shared["mcmc-explore-auto"])
    return replace(spec, entries=entries, seeds=(0,), name="cap-sweep")


DYNAMIC_SEEDS = (0, 1, 2)


def dynamic() -> BenchSpec:
    """The paper's 4DGS experiment at CPU scale: the three dynamic methods and the count control
    on the built-in dynamic scene, three seeds, at the dynamic methods' step budget."""
    from exploregs_plugin.method_configs import DYNAMIC_STEPS

    return BenchSpec(entries=DYNAMIC_ENTRIES, scenes=(BenchScene("dynamic", "builtin:dynamic"),),
                     seeds=DYNAMIC_SEEDS, steps=DYNAMIC_STEPS, eval_count=5, name="dynamic", baseline="4d-default")


DNERF_SCENE = "lego-dnerf-tiny"
"""The D-NeRF lego scene at 100x100 in ../shared/scenes (50 train, 20 test frames, RGB on black)."""
DNERF_ENTRIES = ("4d-default", "4d-split", "4d-seedsplit", "default", "seedsplit")
DNERF_STEPS = 600
"""Under a third of the dynamic methods' 2000 steps, chosen to keep the 15 runs near 40 minutes
with --jobs 2 on the 2-core machine; under the load of docs/results.md they took 91 minutes. The
schedule's fractions keep its shape (a 60-step warm-up, densifications at steps 100 and 200)."""


def dnerf(root: Path | None = None) -> BenchSpec:
    """D-NeRF (monocular video, Blender layout): the three dynamic methods on the tiny lego, and
    the static Default and Seed+Split on the same frames (which ignore time), three seeds each;
    the paired differences are taken against 4d-default."""
    path = (Path(root) if root is not None else shared_scenes_root()) / DNERF_SCENE
    if not path.is_dir():
        raise BenchSpecError(f"dnerf preset: {path} is absent; nothing to run")
    return BenchSpec(entries=_entries(DNERF_ENTRIES), scenes=(BenchScene("lego", str(path)),),
                     seeds=DYNAMIC_SEEDS, steps=DNERF_STEPS, eval_count=4, name="dnerf", baseline="4d-default")


def _analysis(name: str, scenes: tuple[str, ...]) -> BenchSpec:
    """An eg-analyze ablation (branch ablation, depth supervision, split ablation) as a bench."""
    from exploregs_plugin.analysis.ablations import EXPERIMENTS

    entries = tuple(BenchEntry(r.name, r.method, r.overrides, r.description) for r in EXPERIMENTS[name])
    return BenchSpec(entries=entries, scenes=tuple(BenchScene(s, f"builtin:{s}") for s in scenes),
                     seeds=(0,), steps=ANALYSIS_STEPS, eval_count=4, name=name,
                     baseline=ANALYSIS_BASELINES.get(name, "default"))


PRESETS = {
    "quick": quick,
    "standard": standard,
    "real": real,
    "full": full,
    "full-explore": full_explore,
    "cap-sweep": cap_sweep,
    "real-gpu": real_gpu,
    "dynamic": dynamic,
    "dnerf": dnerf,
    "time-to-quality": time_to_quality,
    # the paper's ablations (docs/analysis.md): every subset of position-gradient branches switched
    # off, depth supervision (ground truth and a noisy, biased "monocular" map), and n_split /
    # gradient-threshold sweeps for the PSNR-against-Gaussians plot
    "branch-ablation": lambda: _analysis("branch-ablation", ("default",)),
    "depth-supervision": lambda: _analysis("depth-supervision", STANDARD_SCENES),
    "split-ablation": lambda: _analysis("split-ablation", ("combined",)),
}


def preset(name: str) -> BenchSpec:
    if name not in PRESETS:
        raise BenchSpecError(f"unknown preset {name!r}; presets: {', '.join(PRESETS)}")
    return PRESETS[name]()
