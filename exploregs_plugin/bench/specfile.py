"""Building a BenchSpec from a preset, a YAML/JSON spec file and command-line options.

Spec file (YAML or JSON; every key optional except that methods and scenes must come from
somewhere: the file, its ``preset`` or the command line)::

    preset: quick                 # start from a preset, then change it
    steps: 2000
    seeds: [0, 1, 2]
    eval_count: 5
    baseline: default             # entry for the paired differences
    methods:
      - default                   # a named entry or a registered method
      - name: seed50              # a new row
        method: seed              # a named entry or a method (exploregs-seed)
        overrides: --strategy.seeding.n-seed 50
        description: Seeding with 50 seeds per step
    scenes:
      - builtin:farside
      - {name: beer, data: ../shared/scenes/beer, data_factor: 8, options: --datamanager.test-every 8}
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

from exploregs_plugin.bench.presets import entry_from_arg, preset
from exploregs_plugin.bench.spec import (
    BenchEntry,
    BenchScene,
    BenchSpec,
    BenchSpecError,
    check_mapping,
    check_name,
    scene_from_arg,
    scene_from_dict,
    split_args,
)

SPEC_KEYS = {"preset", "steps", "seeds", "eval_count", "baseline", "methods", "scenes"}


def entry_from_dict(d: Any, where: str) -> BenchEntry:
    if isinstance(d, str):
        return entry_from_arg(d)
    check_mapping(d, where, "method", "name", ("name", "method", "overrides", "description"))
    name = check_name("entry", str(d["name"]))
    base = entry_from_arg(f"{name}={d['method']}") if "method" in d else entry_from_arg(name)
    return BenchEntry(name, base.method, base.overrides + tuple(split_args(d.get("overrides"))),
                      str(d.get("description", base.description)))


def read_spec_file(path: Path) -> dict[str, Any]:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise BenchSpecError(f"spec file {path}: cannot read it: {err}") from err
    except UnicodeDecodeError as err:  # a PLY, a checkpoint, an image: not a YAML or JSON spec
        raise BenchSpecError(f"spec file {path}: not a YAML or JSON text file") from err
    if path.suffix == ".json":
        try:
            data = json.loads(text)
        except ValueError as err:
            raise BenchSpecError(f"spec file {path}: not valid JSON: {err}") from err
    else:
        import yaml

        from exploregs_plugin.io.config_files import read_yaml

        try:
            data = read_yaml(text)
        except yaml.YAMLError as err:
            raise BenchSpecError(f"spec file {path}: not valid YAML: {err}") from err
    if not isinstance(data, dict):
        raise BenchSpecError(f"spec file {path}: expected a mapping at the top, got {type(data).__name__}")
    unknown = set(data) - SPEC_KEYS
    if unknown:
        raise BenchSpecError(f"spec file {path}: unknown keys {sorted(unknown)} "
                             f"(known: {', '.join(sorted(SPEC_KEYS))})")
    return data


def _int_list(value: Any, where: str) -> tuple[int, ...]:
    if isinstance(value, int) and not isinstance(value, bool):
        return (value,)
    if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise BenchSpecError(f"{where}: expected a list of integers, got {value!r}")
    return tuple(value)


def _with_args(items: tuple[Any, ...], specs: tuple[str, ...], kind: str, field_name: str) -> tuple[Any, ...]:
    """Append ``NAME:ARGS`` arguments to the named items' ``field_name`` (overrides / options)."""
    items = list(items)
    names = [i.name for i in items]
    for text in specs:
        name, sep, args = text.partition(":")
        if not sep or not name:
            flag, example = (("override", "seed:--strategy.seeding.n-seed 50") if kind == "entry"
                             else ("scene-option", "farside:--data-factor 2"))
            raise BenchSpecError(f"--{flag} {text!r}: expected '{kind.upper()}:ARGS', e.g. '{example}'")
        if name not in names:
            raise BenchSpecError(f"{text!r} names {kind} {name!r}, which is not in the bench ({', '.join(names)})")
        k = names.index(name)
        items[k] = replace(items[k], **{field_name: getattr(items[k], field_name) + tuple(split_args(args))})
    return tuple(items)


def compose(
    preset_name: str | None = None,
    spec_file: Path | None = None,
    methods: tuple[str, ...] | None = None,
    scenes: tuple[str, ...] | None = None,
    seeds: tuple[int, ...] | None = None,
    steps: int | None = None,
    eval_count: int | None = None,
    baseline: str | None = None,
    overrides: tuple[str, ...] = (),
    scene_options: tuple[str, ...] = (),
    data_factor: int | None = None,
) -> BenchSpec:
    """Preset, then spec file, then command-line options; each later source replaces the keys it
    gives. ``overrides`` (``ENTRY:ARGS``) and ``scene_options`` (``SCENE:ARGS``) add arguments;
    ``data_factor`` adds ``--data-factor N`` to every scene."""
    data = read_spec_file(spec_file) if spec_file is not None else {}
    if preset_name is not None and data.get("preset") not in (None, preset_name):
        raise BenchSpecError(f"preset {preset_name!r} given, but the spec file names preset {data['preset']!r}")
    base_name = preset_name or data.get("preset")
    fields: dict[str, Any] = {}
    if base_name is not None:
        base = preset(str(base_name))
        fields = {"entries": base.entries, "scenes": base.scenes, "seeds": base.seeds, "steps": base.steps,
                  "eval_count": base.eval_count, "baseline": base.baseline, "name": base.name, "notes": base.notes}
    where = f"spec file {spec_file}"
    if "methods" in data:
        fields["entries"] = tuple(entry_from_dict(d, f"{where} methods[{i}]")
                                  for i, d in enumerate(data["methods"] or []))
    if "scenes" in data:
        fields["scenes"] = tuple(scene_from_dict(d, f"{where} scenes[{i}]") for i, d in enumerate(data["scenes"] or []))
    if "seeds" in data:
        fields["seeds"] = _int_list(data["seeds"], f"{where} seeds")
    for key in ("steps", "eval_count"):
        if key in data:
            fields[key] = _int_list(data[key], f"{where} {key}")[0]
    if "baseline" in data:
        fields["baseline"] = str(data["baseline"])
    if methods is not None:
        # a name the preset (or spec file) defines is its entry, with its overrides: `eg-bench full
        # --methods default seedsplit` runs the full bench's Default and Seed+Split, at its threshold
        # and budget, not the generic entries of those names
        defined = {e.name: e for e in fields.get("entries", ())}
        fields["entries"] = tuple(defined[m] if m in defined else entry_from_arg(m) for m in methods)
    if scenes is not None:
        fields["scenes"] = tuple(scene_from_arg(s) for s in scenes)
    for key, value in (("seeds", seeds), ("steps", steps), ("eval_count", eval_count), ("baseline", baseline)):
        if value is not None:
            fields[key] = tuple(value) if key == "seeds" else value
    if "entries" not in fields or "scenes" not in fields:
        raise BenchSpecError("say what to run: a preset (quick, standard, real), --spec FILE, "
                             "or --methods ... --scenes ...")
    if spec_file is not None or methods is not None or scenes is not None or overrides or scene_options:
        fields["name"] = f"{base_name}+custom" if base_name else "custom"
    fields["entries"] = _with_args(fields["entries"], overrides, "entry", "overrides")
    scenes_t: tuple[BenchScene, ...] = fields["scenes"]
    if data_factor is not None:
        scenes_t = tuple(replace(s, options=s.options + ("--data-factor", str(data_factor))) for s in scenes_t)
    fields["scenes"] = _with_args(scenes_t, scene_options, "scene", "options")
    return BenchSpec(**fields)
