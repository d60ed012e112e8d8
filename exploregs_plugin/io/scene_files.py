"""One entry point for every Gaussian scene file: standard 3DGS PLY, PlayCanvas compressed PLY,
antimatter15 ``.splat`` and Niantic ``.spz``.

Writing maps the model's parameters from the normalised training frame to the dataset's
original one and drops Gaussians with a non-finite value, exactly as
:func:`exploregs_plugin.io.ply.export_ply` does, then hands them to the format's writer. Reading
tells the format from the file's first bytes (``ply``, gzip or NGSP magic; a ``.splat`` has
none, so its suffix decides), and a ``.ply`` whose header has packed/chunk elements reads as a
compressed PLY.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

from torch import Tensor

from exploregs_plugin.io.compressed_ply import (
    is_compressed_ply,
    read_compressed_ply,
    write_compressed_ply,
)
from exploregs_plugin.io.packing import read_file_bytes
from exploregs_plugin.io.ply import (
    PlyExport,
    PlyFormatError,
    PlyScene,
    check_shapes,
    drop_nonfinite,
    export_ply,
    read_ply,
    scene_read,
    to_original_frame,
)
from exploregs_plugin.io.splat import read_splat, write_splat
from exploregs_plugin.io.spz import GZIP_MAGIC, SH1_BITS, SH_REST_BITS, read_spz, write_spz
from exploregs_plugin.io.spz import MAGIC as SPZ_MAGIC

SceneFormat = Literal["ply", "splat", "spz", "compressed-ply"]
SCENE_FORMATS: tuple[str, ...] = ("ply", "splat", "spz", "compressed-ply")
SUFFIXES = {"compressed-ply": ".compressed.ply", "ply": ".ply", "splat": ".splat", "spz": ".spz"}
"""The file name ending of each format (checked longest first: .compressed.ply before .ply)."""
ANTIALIASED_COMMENT = "SplatRenderMode: mip"
"""PLY header comment for a scene trained with the antialiased filter (Brush's spelling, which
splat-transform reads and writes)."""


@dataclass(frozen=True)
class SceneExport(PlyExport):
    """What :func:`write_scene` wrote: ``format``, the file's ``size_bytes``, and as for a PLY
    ``written`` / ``dropped`` Gaussians and ``sh_degree`` (the degree the file holds: 0 for .splat)."""

    format: str = "ply"
    size_bytes: int = 0


def suffix_format(path: str | Path) -> str | None:
    """The format a file name's ending names, or None for another ending."""
    name = Path(path).name.lower()
    for fmt, suffix in SUFFIXES.items():
        if name.endswith(suffix):
            return fmt
    return None


def format_for(path: str | Path, requested: str | None = None, *, default: str | None = None) -> str:
    """The format to write ``path`` in: ``requested`` (a --format), else the one its suffix names,
    else ``default``. A requested format that contradicts the suffix is an error (a compressed
    PLY may end in plain ``.ply``); so is no format at all."""
    if requested is not None and requested not in SCENE_FORMATS:
        raise ValueError(f"unknown scene format {requested!r}; one of {', '.join(SCENE_FORMATS)}")
    named = suffix_format(path)
    if requested is None:
        if named is None and default is None:
            raise PlyFormatError(path, f"cannot tell the scene format from the name; end it in "
                                       f"{', '.join(SUFFIXES.values())} or give the format")
        return named or default  # type: ignore[return-value]
    if named is not None and named != requested and not (requested == "compressed-ply" and named == "ply"):
        raise PlyFormatError(path, f"format {requested} does not match the suffix, which names {named}; "
                                   f"end the name in {SUFFIXES[requested]} or drop the format")
    return requested


def write_scene(path: Path, params: Mapping[str, Tensor], normalization: Any = None, *, fmt: str | None = None,
                comments: Sequence[str] = (), antialiased: bool = False, text: bool = False,
                spz_sh_bits: tuple[int, int] = (SH1_BITS, SH_REST_BITS)) -> SceneExport:
    """Write raw parameters (normalised frame) to ``path`` in ``fmt`` (None: from the suffix, PLY
    for another suffix), in the original frame of ``normalization`` (None: as they are).

    comments: header comments (PLY formats only; .splat and .spz have no place for them).
    antialiased: the scene was trained with the antialiased filter: .spz sets its flag, the PLY
    formats carry ``comment SplatRenderMode: mip``; .splat cannot say it. text: ASCII PLY.
    spz_sh_bits: .spz's bits per SH coefficient of band 1 and bands 2-3 (the reference's 5 and 4).
    """
    path = Path(path)
    fmt = format_for(path, fmt, default="ply")
    if text and fmt != "ply":
        raise PlyFormatError(path, f"an ASCII file is only possible for ply, not {fmt}")
    header = [*comments, *([ANTIALIASED_COMMENT] if antialiased else [])]
    if fmt == "ply":
        result = export_ply(path, params, normalization, text=text, comments=header)
        return SceneExport(result.path, result.written, result.dropped, result.sh_degree, fmt, path.stat().st_size)
    degree = check_shapes(params, path)
    mapped, dropped = drop_nonfinite(to_original_frame(params, normalization))
    if mapped["means"].shape[0] == 0:
        raise PlyFormatError(path, f"no Gaussians to write ({dropped} had non-finite values)")
    if fmt == "splat":
        size, degree = write_splat(path, mapped), 0
    elif fmt == "spz":
        size = write_spz(path, mapped, antialiased=antialiased, sh_bits=spz_sh_bits)
    else:
        size = write_compressed_ply(path, mapped, header)
    return SceneExport(path, int(mapped["means"].shape[0]), dropped, degree, fmt, size)


def content_format(path: Path) -> str:
    """The format of an existing file, from its first bytes; else (a .splat has no header, or
    the file is damaged) the one its suffix names, whose reader then says what is wrong."""
    path = Path(path)
    head = read_file_bytes(path, "a scene file")[:4]
    if head[:3] == b"ply":
        return "compressed-ply" if is_compressed_ply(path) else "ply"
    if head[:2] == GZIP_MAGIC or (len(head) == 4 and int.from_bytes(head, "little") == SPZ_MAGIC):
        return "spz"
    named = suffix_format(path)
    if named is None:
        raise PlyFormatError(path, f"is not a scene file: no PLY, gzip or NGSP (.spz) header, and not named "
                                   f"{', '.join(SUFFIXES.values())}")
    return named


def read_scene(path: Path, normalization: Any = None, *, keep_nonfinite: bool = False) -> PlyScene:
    """Read any scene file (format from its content) -> :class:`PlyScene`.

    normalization: when given, map the file's coordinates into that normalised frame, as
    :func:`exploregs_plugin.io.ply.read_ply` does. Gaussians with a non-finite value are dropped
    and counted unless ``keep_nonfinite``.
    """
    path = Path(path)
    fmt = content_format(path)
    if fmt == "ply":
        return read_ply(path, normalization, keep_nonfinite=keep_nonfinite)
    reader = {"splat": read_splat, "spz": read_spz, "compressed-ply": read_compressed_ply}[fmt]
    params, degree = reader(path)
    return scene_read(path, params, degree, normalization, keep_nonfinite)
