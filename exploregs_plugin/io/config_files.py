"""Config plumbing shared by every part: YAML round trip of nested dataclass configs.

A run folder's ``config.yml`` must rebuild exactly the config that trained it, including
strategies and methods that come from other installed packages. Each dataclass is therefore
written with its import path (``_type: module:QualName``) and rebuilt by importing it.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import re
import textwrap
from pathlib import Path, PurePath
from typing import Any

import yaml

from exploregs_plugin.io.atomic import atomic_write_text

_TYPE_KEY = "_type"

# libyaml's parser and emitter where PyYAML has them (its wheels do): the same documents as its
# pure-Python safe_load and safe_dump, read about 8x and written about 5x faster (a run's
# config.yml: 23 -> 3 ms to read on the 2-core machine), which every eg-train --resume, eg-eval,
# eg-export and eg-render start pays.
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_SAFE_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def read_yaml(text: str) -> Any:
    """``yaml.safe_load(text)`` (the safe tags only), parsed by libyaml where PyYAML has it;
    raises ``yaml.YAMLError``."""
    return yaml.load(text, Loader=_SAFE_LOADER)


def yaml_text(data: Any) -> str:
    """``yaml.safe_dump(data, sort_keys=False)``, written by libyaml where PyYAML has it."""
    return yaml.dump(data, Dumper=_SAFE_DUMPER, sort_keys=False)


def config_to_dict(value: Any) -> Any:
    """Plain YAML-able structure for a (nested) dataclass config."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        out: dict[str, Any] = {_TYPE_KEY: f"{cls.__module__}:{cls.__qualname__}"}
        for f in dataclasses.fields(value):
            out[f.name] = config_to_dict(getattr(value, f.name))
        return out
    if isinstance(value, PurePath):
        return {_TYPE_KEY: "path", "value": str(value)}
    if isinstance(value, enum.Enum):
        cls = type(value)
        return {_TYPE_KEY: f"{cls.__module__}:{cls.__qualname__}", "value": value.value}
    if isinstance(value, tuple):
        return {_TYPE_KEY: "tuple", "value": [config_to_dict(v) for v in value]}
    if isinstance(value, list):
        return [config_to_dict(v) for v in value]
    if isinstance(value, dict):
        return {str(k): config_to_dict(v) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"cannot write config value of type {type(value).__name__}: {value!r}")


MOVED_TYPES: dict[str, str] = {
    "exploregs_plugin.data.depth_supervision:DepthSupervisionConfig":
        "exploregs_plugin.analysis.depth_degradation:DepthSupervisionConfig",
    # the gsplat adapters are named by direction (gsplat's strategies inside eg-train: from_gsplat)
    "exploregs_plugin.integrations.gsplat_in_eg:GsplatDefaultStrategy":
        "exploregs_plugin.integrations.from_gsplat:GsplatDefaultStrategy",
    "exploregs_plugin.integrations.gsplat_in_eg:GsplatMCMCStrategy":
        "exploregs_plugin.integrations.from_gsplat:GsplatMCMCStrategy",
}
"""Config classes that moved to another module since configs were saved: old path -> new path."""

MOVED_MODULES: dict[str, str] = {
    # renamed so that each name says what it holds (the noise itself, the strategy that uses it,
    # the operators' contract beside the row operations), with every class in them
    "exploregs_plugin.strategies.ray": "exploregs_plugin.strategies.ray_perturbation",
    "exploregs_plugin.strategies.perturbation": "exploregs_plugin.strategies.position_noise",
    "exploregs_plugin.strategies.operator": "exploregs_plugin.strategies.operator_contract",
    # the package root's loose modules went into folders by what they are (2026-11-29):
    # engine/ (the loop and what watches it), evaluation/, runtime/ (devices, ranks, threads), io/
    **{f"exploregs_plugin.{name}": f"exploregs_plugin.engine.{name}" for name in (
        "trainer", "training_loop", "pipeline", "stopping", "watches", "run_folder", "thread_follower", "nonfinite",
        "collapse", "run_logger", "count_trial", "loss_terms")},
    "exploregs_plugin.evaluation": "exploregs_plugin.evaluation.metrics",
    "exploregs_plugin.rank_evaluation": "exploregs_plugin.evaluation.ranks",
    "exploregs_plugin.perceptual": "exploregs_plugin.evaluation.perceptual",
    **{f"exploregs_plugin.{name}": f"exploregs_plugin.runtime.{name}" for name in ("device", "distributed", "threads")},
    "exploregs_plugin.config_io": "exploregs_plugin.io.config_files",
}
"""Modules whose config classes moved whole, since configs were saved: old module -> new module
(``exploregs_plugin.strategies.ray:RayPerturbationStrategy`` is
``exploregs_plugin.strategies.ray_perturbation:RayPerturbationStrategy``)."""


def current_type(spec: str) -> str:
    """Where the config class that a saved config names (``module:QualName``) lives now."""
    spec = MOVED_TYPES.get(spec, spec)
    module_name, sep, qualname = spec.partition(":")
    return f"{MOVED_MODULES[module_name]}{sep}{qualname}" if module_name in MOVED_MODULES else spec


def _import_type(spec: str) -> Any:
    spec = current_type(spec)
    module_name, _, qualname = spec.partition(":")
    try:
        obj: Any = importlib.import_module(module_name)
    except ImportError as err:
        raise ValueError(
            f"config names type {spec!r}, but module {module_name!r} cannot be imported "
            f"(is the package that provides it installed?): {err}"
        ) from err
    for part in qualname.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"config names type {spec!r}, which does not exist")
        obj = getattr(obj, part)
    return obj


REMOVED_FIELDS: dict[str, dict[str, tuple[Any, str]]] = {
    "exploregs_plugin.model.gaussians:GaussianModelConfig": {
        "detach_paths": ((), "the branch ablation's switch is a field of the method exploregs-branch-ablation "
                             "(eg-train exploregs-branch-ablation --model.detach-paths ...)"),
    },
    "exploregs_plugin.engine.trainer:TrainerConfig": {
        "grad_branches_every": (0, "the live branch-gradient curves are the method exploregs-grad-branches "
                                   "(eg-train exploregs-grad-branches --strategy NAME --grad-branches-every N)"),
        "grad_branches_views": (lambda old: True, "exploregs-grad-branches --grad-branches-views"),
    },
    "exploregs_plugin.strategies.mcmc:MCMCStrategy": {
        # the windowed growth contrast of cap_max 'validated' was replaced by the paired cut; its two
        # settings meant nothing for any other cap, and a run that used them has its count already
        "count_window": (lambda old: True, "cap_max 'validated' now decides by a paired cut (--strategy.count-cuts)"),
        "count_min_gain": (lambda old: True, "cap_max 'validated' now decides by a paired cut (--strategy.count-tolerance)"),
    },
    "exploregs_plugin.engine.pipeline:PipelineConfig": {
        "depth_supervision": (lambda old: not old.active,
                              "degraded depth maps are the method exploregs-mono-depth (eg-train "
                              "exploregs-mono-depth --strategy NAME --depth-supervision.noise-std ...)"),
    },
}
"""Fields a config class no longer has, by the class that had them (its subclasses' saved configs
included): (the value that meant "off", or a test of the saved value that says it was off; where
the setting went). A saved config whose value was off loads (the field is dropped); any other
value is refused with one line that says where it went."""


ADDED_FIELDS: dict[str, dict[str, Any]] = {
    "exploregs_plugin.strategies.default:DefaultStrategy": {
        "grow_grad2d_height": None,  # the threshold as given at every image height
        "prune_weight_share": 0.0,  # no significance prune while growing
        "final_weight_share": 0.0,  # no cut after the last step
        "final_cut_tolerance": 0.0,  # the cut at the fixed share alone
        "split_absgrad2d": None,  # splits by the summed gradient alone
        "settled_cut_iter": 0,  # the cut after the last step only
        "settled_cut_frac": 2.0 / 3.0,  # where an unset settled_cut_iter fell
        "settled_cut_tolerance": None,  # the settled cut checked as the end-of-run cut
    },
}
"""Fields a config class gained after runs were saved without them, by the class that has them
(its subclasses' saved configs included): the value that does what the run did before the field
existed. A saved config without the field loads with it, so an old run resumes as it trained."""


def _with_added(cls: type, names: set[str], value: dict[str, Any]) -> dict[str, Any]:
    """``value`` with the fields that ``cls`` gained since it was saved set to their old behaviour."""
    for base in cls.__mro__:
        for name, old in ADDED_FIELDS.get(f"{base.__module__}:{base.__qualname__}", {}).items():
            if name in names and name not in value:
                value = {**value, name: old}
    return value


def _without_removed(cls: type, names: set[str], spec: str, value: dict[str, Any]) -> dict[str, Any]:
    """``value`` without the removed fields of ``cls`` and its bases that ``cls`` does not have
    again (``names``: its fields)."""
    for base in cls.__mro__:
        for name, (off, moved) in REMOVED_FIELDS.get(f"{base.__module__}:{base.__qualname__}", {}).items():
            if name in value and name not in names:
                old = config_from_dict(value[name])
                if not (off(old) if callable(off) else old == off):
                    raise ValueError(f"config for {spec}: field {name!r} ({old!r}) is gone: {moved}")
                value = {k: v for k, v in value.items() if k != name}
    return value


_SEEDING = {"n_seed": "n_seed", "seed_every": "every", "seed_box_mode": "box_mode", "seed_box_quantile": "box_quantile",
            "seed_opacity_base": "opacity_base", "seed_opacity_gain": "opacity_gain",
            "seed_prune_scale3d": "prune_scale3d", "seed_min_scale": "min_scale", "seed_prune_opa": "prune_opa",
            "seed_grace": "grace", **{f"guide_{name}": f"guide_{name}" for name in
                                      ("cell", "power", "near", "far", "depth", "opacity", "scale")}}
_NOISE = {"noise_lr": "lr", "noise_gate_k": "gate_k", "noise_gate_t": "gate_t"}
MOVED_FIELDS: dict[str, dict[str, str]] = {
    "exploregs_plugin.strategies.exploration:ExplorationStrategy": {
        **{old: f"seeding.{new}" for old, new in _SEEDING.items()},
        "n_split": "splitting.n_split", "split_every": "splitting.every",
        "occlusion_t_floor": "splitting.occlusion_t_floor", "occlusion_decay": "splitting.occlusion_decay",
        **{old: f"noise.{new}" for old, new in _NOISE.items()},
    },
    "exploregs_plugin.strategies.mcmc:MCMCStrategy": {
        **{old: f"noise.{new}" for old, new in _NOISE.items()}, "noise_mode": "noise.mode",
    },
}
"""Fields that moved into a nested config, by the class that has the nested field now (its
subclasses included): old name -> "field.name". The strategies' operators became nested configs
(``--strategy.n-seed`` is ``--strategy.seeding.n-seed``); a saved config with the old flat fields
loads into the nested ones, starting from the nested field's default."""


def _field_default(cls: type, name: str) -> Any:
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


def _with_moved(cls: type, names: set[str], value: dict[str, Any]) -> dict[str, Any]:
    """``value`` with the flat fields that moved into a nested field of ``cls`` put there."""
    for base in cls.__mro__:
        for old, new in MOVED_FIELDS.get(f"{base.__module__}:{base.__qualname__}", {}).items():
            head, _, leaf = new.partition(".")
            if old not in value or old in names or head not in names:
                continue  # not saved, still a field, or not a field of this class: refused below as unknown
            value = dict(value)
            nested = value.get(head)
            if not isinstance(nested, dict):
                nested = config_to_dict(_field_default(cls, head))
            value[head] = {**nested, leaf: value.pop(old)}
    return value


def upgraded(value: Any) -> Any:
    """A written config (``config_to_dict``'s layout) with the fields that moved since it was
    written put where they are now (:data:`MOVED_FIELDS`), at every level; types that cannot be
    imported are left as they are."""
    if isinstance(value, list):
        return [upgraded(v) for v in value]
    if not isinstance(value, dict):
        return value
    value = {k: upgraded(v) for k, v in value.items()}
    spec = value.get(_TYPE_KEY)
    if not isinstance(spec, str) or ":" not in spec:
        return value
    if current_type(spec) != spec:
        spec = value[_TYPE_KEY] = current_type(spec)
    try:
        cls = _import_type(spec)
    except ValueError:
        return value
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        return value
    return _with_moved(cls, {f.name for f in dataclasses.fields(cls) if f.init}, value)


def config_from_dict(value: Any) -> Any:
    """Inverse of :func:`config_to_dict`."""
    if isinstance(value, list):
        return [config_from_dict(v) for v in value]
    if not isinstance(value, dict):
        return value
    if _TYPE_KEY not in value:
        return {k: config_from_dict(v) for k, v in value.items()}
    spec = value[_TYPE_KEY]
    if spec == "path":
        return Path(value["value"])
    if spec == "tuple":
        return tuple(config_from_dict(v) for v in value["value"])
    cls = _import_type(spec)
    if isinstance(cls, type) and issubclass(cls, enum.Enum):
        return cls(value["value"])
    if not dataclasses.is_dataclass(cls):
        raise ValueError(f"config type {spec!r} is not a dataclass")
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    value = _with_added(cls, names, _without_removed(cls, names, spec, _with_moved(cls, names, value)))
    unknown = set(value) - names - {_TYPE_KEY}
    if unknown:
        raise ValueError(f"config for {spec} has unknown fields: {sorted(unknown)}")
    kwargs = {k: config_from_dict(v) for k, v in value.items() if k in names}
    return cls(**kwargs)


def tyro_error_text(captured: str) -> str:
    """tyro's boxed error message as one line: the frame, the usage hint and tyro's internal
    wrapper name (``__tyro-dummy-inner__``) dropped."""
    lines = []
    # the frame's characters and rules go; a dash that starts a wrapped line stays ("got -1")
    for line in (ln.strip("│╭╰╮╯─ \t") for ln in captured.splitlines()):
        if set(line) <= {"-"}:
            continue
        if line.startswith(("For full helptext", "Argument helptext")):  # the hint (which may wrap) ends the message
            break
        if line and not line.startswith("usage:"):
            lines.append(line)
    text = " ".join(dict.fromkeys(lines)).replace("__tyro-dummy-inner__.", "")
    # "Unrecognized options Unrecognized options: --data, PATH, ... Arguments similar to ..." -> the
    # options alone (a flag of another command, with its value): "unrecognized option --data"
    unknown = re.match(r"^Unrecognized options Unrecognized options: (.*?)(?: Arguments similar to .*)?"
                       r"(?: Available subcommands: (.*))?$", text)
    misplaced = re.match(r"^Unrecognized options Unrecognized or misplaced options: (.*)$", text)
    if unknown or misplaced:  # a subcommand's misplaced flag is named without its dashes
        given = (unknown.group(1).split(", ") if unknown else
                 [item if not re.fullmatch(r"\w+", item) else f"--{item.replace('_', '-')}"
                  for item in re.findall(r"(\S+) \(applied to [^)]*\)", misplaced.group(1))])
        flags = [item for item in given if item.startswith("-")] or given
        words = f"unrecognized {'option' if flags[0].startswith('-') else 'argument'}{'s' * (len(flags) > 1)} "
        subcommands = f" (a subcommand comes first: {unknown.group(2)})" if unknown and unknown.group(2) else ""
        return words + ", ".join(flags) + subcommands
    text = re.sub(r"^Invalid choice invalid choice", "invalid choice", text)
    # "Required options Missing from X: PATH A run folder ... (required)" -> "missing PATH"
    missing = re.match(r"^Required options Missing from [^:]*: (\S+)", text)
    if missing:
        return f"missing {missing.group(1)}"
    subcommand = re.match(r"^Missing subcommand Expected one of \{(.*)\}\.?$", text)
    if subcommand:
        return f"missing a subcommand: one of {subcommand.group(1)}"
    # Python's conversion errors in words: "--seed: expected an integer, got 'abc'"
    text = re.sub(r"^Value error Error parsing (--[\w.-]+): invalid literal for int\(\) with base 10: (.*)$",
                  r"\1: expected an integer, got \2", text)
    text = re.sub(r"^Value error Error parsing (--[\w.-]+): could not convert string to float: (.*)$",
                  r"\1: expected a number, got \2", text)
    # "Value error Error parsing pipeline.strategy: X" -> "--strategy: X" (the flag group's name);
    # no group name where there is no such flag (the command's own config class, TrainerConfig) or
    # the message names its flag itself ("--options: --num-frames: ..." -> "--num-frames: ...")
    parsing = re.match(r"^Value error Error parsing (?:pipeline\.)?([\w.]+): (.*)$", text)
    if parsing:
        group, message = parsing.groups()
        if group[:1].isupper() or message.startswith("--"):
            return message
        return f"--{group.replace('_', '-')}: {message}"
    return text


def save_config(config: Any, path: Path) -> None:
    """Write ``config`` as YAML to ``path`` (atomically: temporary file, then rename)."""
    atomic_write_text(path, yaml_text(config_to_dict(config)))


def load_config(path: Path) -> Any:
    """Read a config written by :func:`save_config`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    try:
        data = read_yaml(path.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{path} is not valid YAML: {err}") from err
    if not isinstance(data, dict) or _TYPE_KEY not in data:
        raise ValueError(f"{path} is not an ExploreGS config (no top-level {_TYPE_KEY!r})")
    return config_from_dict(data)


_LIST_ITEM = re.compile(r"([-*]|\d+[.)])\s")


def join_help_lines(text: str) -> str:
    """A docstring as help text: the lines of each paragraph joined into one (the terminal
    wraps them), blank lines kept as paragraph breaks; a list item ("- ", "1. ") or a line
    indented deeper than the paragraph (an example) starts a new line."""
    paragraphs = []
    for paragraph in re.split(r"\n[ \t]*\n", text.strip("\n")):
        first, *rest = paragraph.split("\n")
        rest = textwrap.dedent("\n".join(rest)).split("\n") if rest else []
        lines = [first.strip()]
        for line in rest:
            if line[:1].isspace() or _LIST_ITEM.match(line):
                lines.append(line.rstrip())
            else:
                lines[-1] = f"{lines[-1]} {line.strip()}"
        paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs).strip()


_BOX_TOP = re.compile(r"^[╭┌]─+ (.*?) ─+[╮┐]\s*$")
_BOX_LINE = re.compile(r"^[│|] (.*?)\s*[│|]\s*$")
_DEFAULT = re.compile(r"\s*\(default: (.*)\)\s*$")
_SENTENCE_END = re.compile(r"(?<=[.;])\s")


def _is_rule(line: str) -> bool:
    return bool(line) and set(line) <= set("─-")


def _flag_line(name: str, description: str, width: int) -> str:
    """``  --flag TYPE   First sentence... [default]`` in at most ``width`` characters."""
    found = _DEFAULT.search(description)
    value = found.group(1) if found else None
    default = "" if value is None else f" [{value if len(value) <= 24 else value[:21] + '...'}]"
    first = _SENTENCE_END.split(_DEFAULT.sub("", description), maxsplit=1)[0].rstrip(".;")
    line = f"  {name:<30} {first}"
    room = max(width - len(default), len(name) + 8)  # the flag itself is never cut
    return (line if len(line) <= room else line[:room - 3].rstrip() + "...") + default


def _box_lines(title: str, lines: list[str], width: int) -> list[str]:
    """One tyro box: its title (with the group's description, which comes before a rule line
    when there is one), then a line per flag (a flag starts at the box's edge, its text is
    indented) or per other entry (a subcommand)."""
    rule = next((i for i, line in enumerate(lines) if _is_rule(line.strip())), None)
    about = " ".join(line.strip() for line in lines[:rule]) if rule is not None else ""
    out = [f"{title}:" + (f" {about}" if about else "")]
    flag: list[str] | None = None
    for line in lines[rule + 1 if rule is not None else 0:]:
        if line.startswith("-") and flag is not None and flag[0].endswith(",") and len(flag) == 1:
            flag[0] += f" {line.strip()}"  # a flag's names went on over two lines
        elif line.startswith("-"):
            if flag is not None:
                out.append(_flag_line(flag[0], " ".join(flag[1:]), width))
            flag = [line.strip()]
        elif flag is not None and line.strip():
            flag.append(line.strip())
        elif line.strip():
            out.append(f"  {line.strip()}")
    if flag is not None:
        out.append(_flag_line(flag[0], " ".join(flag[1:]), width))
    return out


def compact_help(text: str, width: int = 100) -> str:
    """tyro's ``--help`` with one line per flag: the flag, the first sentence of its description
    (cut at ``width``) and its default; each box becomes a group title with its description.
    Nothing is dropped but the rest of each description, which ``--help-full`` keeps."""
    out: list[str] = []
    box: tuple[str, list[str]] | None = None
    for raw in text.splitlines():
        top, inside = _BOX_TOP.match(raw), _BOX_LINE.match(raw)
        if top:
            box = (top.group(1), [])
        elif box is not None and inside:
            box[1].append(inside.group(1))
        elif box is not None and raw.startswith(("╰", "└")):
            out += _box_lines(*box, width)
            box = None
        else:
            out.append(raw)
    return "\n".join(out).rstrip() + "\n"


def use_joined_help_lines() -> None:
    """Make tyro join the lines of multi-line docstrings. tyro 1.0 keeps a docstring's line
    break whenever the next line starts with a space or a non-letter, which is every continued
    line of a field docstring in a class body, so ``--help`` broke sentences mid-line where the
    source wraps. Patches tyro's one helper for this (``tyro._strings``; nothing when absent)."""
    try:
        from tyro import _strings
    except ImportError:
        return
    if hasattr(_strings, "remove_single_line_breaks"):
        _strings.remove_single_line_breaks = join_help_lines


def unset(meaning: str) -> Any:
    """A tyro marker for an option whose default is None: ``--help`` says what leaving it unset
    means (``(default: the model's)``) instead of ``(default: None)``. Use as
    ``Annotated[int | None, unset("the model's")] = None``."""
    import tyro

    return tyro.conf.arg(help_behavior_hint=f"(default: {meaning})")
