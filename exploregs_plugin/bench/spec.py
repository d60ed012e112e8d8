"""What a benchmark runs: entries (a method plus overrides), scenes (data plus options), seeds, steps.

An entry's and a scene's overrides are eg-train command-line arguments (``--strategy.seeding.n-seed 50``,
``--data-factor 4``), parsed with tyro against the entry's method config, exactly as ``eg-train``
would parse them, so a typo fails with tyro's message naming the argument.
"""

from __future__ import annotations

import hashlib
import json
import re
import shlex
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from exploregs_plugin.io.config_files import tyro_error_text
from exploregs_plugin.engine.trainer import TrainerConfig

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class BenchSpecError(ValueError):
    """A benchmark specification (preset, CLI arguments or spec file) is invalid."""


def split_args(args: str | list[str] | tuple[str, ...] | None) -> list[str]:
    """Override arguments as a list: a string is split like a shell would (``'--a 1 --b x'``)."""
    if args is None:
        return []
    if isinstance(args, str):
        return shlex.split(args)
    if not all(isinstance(a, str) for a in args):
        raise BenchSpecError(f"override arguments must be strings, got {list(args)!r}")
    return list(args)


def check_name(kind: str, name: str) -> str:
    """Entry and scene names become folder names: letters, digits and ``_.+-`` only."""
    if not _NAME.match(name):
        raise BenchSpecError(f"{kind} name {name!r} must start with a letter or digit and use only "
                             f"letters, digits and '_.+-' (it names a folder)")
    return name


RESULT_REF = re.compile(r"\{([A-Za-z0-9][A-Za-z0-9_.+-]*):(num_gaussians)(?:\*([0-9]+(?:\.[0-9]+)?))?\}")
"""``{ENTRY:num_gaussians}`` in an override: the final count of ENTRY's run (same scene and seed);
``{ENTRY:num_gaussians*0.5}``: that count times a factor, rounded to a whole count (a sweep of
caps around a reference count)."""


def _scaled(value: Any, factor: str | None) -> str:
    """A referenced result as override text, times ``factor`` (rounded to an int) when given."""
    return str(value) if factor is None else str(int(round(float(value) * float(factor))))


@dataclass(frozen=True)
class BenchEntry:
    """One row of the tables: a registered method plus eg-train overrides."""

    name: str
    """Row name and folder name (e.g. ``default-relaxed-prune``)."""
    method: str
    """Registered method (``eg-train --help`` lists them), e.g. ``exploregs-default``."""
    overrides: tuple[str, ...] = ()
    """eg-train arguments applied to the method's config (``--strategy.prune-scale3d 10``). An
    argument ``{ENTRY:num_gaussians}`` is the final Gaussian count of entry ENTRY's run on the
    same scene and seed (``--strategy.cap-max {default:num_gaussians}``): such a run waits for it."""
    description: str = ""
    """One line for the docs and results.md."""
    seeds: tuple[int, ...] | None = None
    """The seeds this entry runs, of the bench's (None: all of them): a control or a costly method
    may run once where the methods compared run three times."""

    def depends_on(self) -> set[str]:
        """Entries whose results this entry's overrides use."""
        return {m.group(1) for arg in self.overrides for m in RESULT_REF.finditer(arg)}

    def resolved(self, value_of: Callable[[str, str], Any]) -> "BenchEntry":
        """The entry with every ``{ENTRY:FIELD}`` (or ``{ENTRY:FIELD*F}``) replaced by
        ``value_of(ENTRY, FIELD)`` (times F)."""
        args = tuple(RESULT_REF.sub(lambda m: _scaled(value_of(m.group(1), m.group(2)), m.group(3)), a)
                     for a in self.overrides)
        return replace(self, overrides=args)


@dataclass(frozen=True)
class BenchScene:
    """One column group of the tables: a dataset plus per-scene eg-train options."""

    name: str
    """Column and folder name (``farside``; a path's folder name unless given)."""
    data: str
    """``builtin:NAME`` or a dataset path (COLMAP folder, transforms.json or its folder)."""
    options: tuple[str, ...] = ()
    """eg-train arguments for every run on this scene (``--data-factor 4``); entry overrides win."""


@dataclass(frozen=True)
class BenchSpec:
    """Entries x scenes x seeds, all with the same step budget."""

    entries: tuple[BenchEntry, ...]
    scenes: tuple[BenchScene, ...]
    seeds: tuple[int, ...] = (0,)
    steps: int = 1000
    """Common step budget of every run (a scene option ``--max-steps`` may change it for one scene)."""
    eval_count: int = 5
    """Periodic test evaluations per run: the points of the PSNR-against-time curves."""
    baseline: str = "default"
    """Entry that paired differences are taken against (same scene, same seed)."""
    name: str = "custom"
    """Preset name, or ``custom``."""
    notes: tuple[str, ...] = field(default_factory=tuple)
    """Lines printed before running (e.g. scenes skipped because their data are absent)."""
    device: str = "cpu"
    """Device of every run (recorded in its config, so a run is reused only on the same device)."""

    def __post_init__(self) -> None:
        if not self.entries:
            raise BenchSpecError("a benchmark needs at least one method entry")
        if not self.scenes:
            raise BenchSpecError("a benchmark needs at least one scene")
        if not self.seeds:
            raise BenchSpecError("a benchmark needs at least one seed")
        if self.steps < 1:
            raise BenchSpecError(f"steps must be >= 1, got {self.steps}")
        if self.eval_count < 1:
            raise BenchSpecError(f"eval_count must be >= 1, got {self.eval_count}")
        for kind, names in (("entry", [e.name for e in self.entries]), ("scene", [s.name for s in self.scenes])):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise BenchSpecError(f"{kind} names must be unique; repeated: {', '.join(dup)}")
        if len(set(self.seeds)) != len(self.seeds):
            raise BenchSpecError(f"seeds must be unique, got {list(self.seeds)}")
        names = {e.name for e in self.entries}
        for e in self.entries:
            if e.seeds is not None and len(set(e.seeds)) != len(e.seeds):
                raise BenchSpecError(f"entry {e.name!r}: seeds must be unique, got {list(e.seeds)}")
            for ref in e.depends_on():
                if ref not in names:
                    raise BenchSpecError(f"entry {e.name!r} uses the result of {ref!r}, which is not in the bench")
                if self.entry(ref).depends_on():
                    raise BenchSpecError(f"entry {e.name!r} uses {ref!r}, which itself waits for another entry")

    def entry(self, name: str) -> BenchEntry:
        for e in self.entries:
            if e.name == name:
                return e
        raise BenchSpecError(f"no entry named {name!r}")

    def seeds_of(self, entry: BenchEntry) -> tuple[int, ...]:
        """The bench's seeds that ``entry`` runs (its own list, within the bench's)."""
        return self.seeds if entry.seeds is None else tuple(s for s in self.seeds if s in entry.seeds)

    def runs(self) -> list[tuple[BenchScene, BenchEntry, int]]:
        """Every (scene, entry, seed), seed outermost, so that a partial bench covers all methods
        of every scene at seed 0 before it starts seed 1."""
        return [(sc, e, s) for s in self.seeds for sc in self.scenes for e in self.entries if s in self.seeds_of(e)]


_STREAM_LOCK = threading.Lock()


def parse_overrides(config: TrainerConfig, args: list[str], where: str) -> TrainerConfig:
    """Apply eg-train arguments to ``config`` through tyro (the same parser eg-train uses);
    ``--strategy NAME`` swaps the strategy first, as in eg-train.

    Raises BenchSpecError naming ``where`` when tyro rejects the arguments."""
    if not args:
        return config
    import contextlib
    import io

    import tyro

    from exploregs_plugin.method_configs import MethodRegistryError, all_methods, strategy_choice, with_strategy

    try:
        args, name = strategy_choice(list(args))
        config = with_strategy(config, name, all_methods() if name else {})
    except MethodRegistryError as err:
        raise BenchSpecError(f"{where}: {err}") from None
    if not args:
        return config

    err = io.StringIO()
    try:
        # The redirect swaps the process-wide streams: serialise it, so two threads can never
        # restore each other's buffer and leave stderr captured for good.
        with _STREAM_LOCK, contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            return tyro.cli(type(config), args=args, default=config)
    except SystemExit as exit_:
        detail = tyro_error_text(err.getvalue()) or f"exit code {exit_.code}"
        raise BenchSpecError(f"{where}: invalid eg-train arguments {shlex.join(args)!r}: {detail}") from None


def build_config(spec: BenchSpec, scene: BenchScene, entry: BenchEntry, seed: int, run_dir: Path) -> TrainerConfig:
    """The complete TrainerConfig of one run: the method's config, the bench fields (data, steps,
    seed, run folder, evaluation count, quiet), then the scene's options, then the entry's overrides."""
    from exploregs_plugin.data.dataparser import BUILTIN_PREFIX
    from exploregs_plugin.method_configs import MethodRegistryError, get_method

    try:
        base = get_method(entry.method).config
    except MethodRegistryError as err:
        raise BenchSpecError(f"entry {entry.name!r}: {err}") from err
    # a dataset path is absolute in the run's config, so the same scene reached from another folder
    # (../shared/scenes/beer from the repository, /work/shared/scenes/beer) is the same run
    data = scene.data if scene.data.startswith(BUILTIN_PREFIX) else str(Path(scene.data).expanduser().resolve())
    config = replace(base, data=data, max_steps=spec.steps, seed=seed, device=spec.device, eval_count=spec.eval_count,
                     quiet=True, tensorboard=False, save_eval_images=False)
    config = parse_overrides(config, list(scene.options), f"scene {scene.name!r} options")
    config = parse_overrides(config, list(entry.overrides), f"entry {entry.name!r} overrides")
    # The bench owns where and under which seed a run happens, whatever the overrides say.
    return replace(config, seed=seed, run_dir=Path(run_dir), resume=None, viewer=False)


VOLATILE_FIELDS = ("run_dir", "output_dir", "resume", "quiet", "num_threads", "viewer", "viewer_config")
"""Top-level TrainerConfig fields that do not change a run's result."""


def comparable(config_dict: dict[str, Any]) -> dict[str, Any]:
    """A written config (``config_to_dict`` or the YAML of a run's job file) without the fields
    that do not change the result."""
    return {k: v for k, v in config_dict.items() if k not in VOLATILE_FIELDS}


def configs_match(old: Any, new: Any) -> bool:
    """Whether a run made with config ``old`` counts as a run of ``new`` (both written dicts).

    Values present in both must be equal (types included); a key present on one side only is a
    field added to or removed from the code since the run was made, so it did not exist then and
    is ignored: a new field must default to the old behaviour, the project's convention for new
    options. Any changed value (steps, seed, an override, a changed default) does not match."""
    if isinstance(old, dict) and isinstance(new, dict):
        return all(configs_match(old[k], new[k]) for k in old.keys() & new.keys())
    if isinstance(old, list) and isinstance(new, list):
        return len(old) == len(new) and all(configs_match(a, b) for a, b in zip(old, new))
    return old == new


def config_fingerprint(config: TrainerConfig) -> str:
    """Short hash of the comparable config (recorded in bench_state.json for reference)."""
    from exploregs_plugin.io.config_files import config_to_dict

    text = json.dumps(comparable(config_to_dict(config)), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def scene_from_arg(text: str) -> BenchScene:
    """``builtin:farside``, ``/path/to/scene`` or ``NAME=DATA``; the name defaults to the
    built-in name or the path's folder name (``transforms.json`` -> its folder)."""
    name, sep, data = text.partition("=")
    if not sep:
        data = text
        if text.startswith("builtin:"):
            name = text.split(":", 1)[1]
        else:
            p = Path(text)
            name = (p.parent.name if p.suffix == ".json" else p.name) or "scene"
    if not data:
        raise BenchSpecError(f"scene {text!r} has no data")
    return BenchScene(name=check_name("scene", name), data=data)


def check_mapping(d: Any, where: str, kind: str, required: str, known: tuple[str, ...]) -> dict[str, Any]:
    """A spec-file item given as a mapping: it has ``required`` and no key outside ``known``."""
    if not isinstance(d, dict) or required not in d:
        raise BenchSpecError(f"{where}: a {kind} is a string or a mapping with '{required}', got {d!r}")
    unknown = set(d) - set(known)
    if unknown:
        raise BenchSpecError(f"{where}: unknown {kind} keys {sorted(unknown)} (known: {', '.join(known)})")
    return d


def scene_from_dict(d: Any, where: str) -> BenchScene:
    if isinstance(d, str):
        return scene_from_arg(d)
    check_mapping(d, where, "scene", "data", ("name", "data", "data_factor", "options"))
    base = scene_from_arg(str(d["data"]))
    options = split_args(d.get("options"))
    if d.get("data_factor") is not None:
        options = ["--data-factor", str(int(d["data_factor"]))] + options
    return BenchScene(name=check_name("scene", str(d.get("name", base.name))), data=base.data, options=tuple(options))
