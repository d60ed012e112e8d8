"""DataManager: the train/test split, images in memory as uint8, a seeded camera order,
background, and ground-truth depths and region masks when the dataset has them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
import tyro
from PIL import Image
from torch import Tensor

from ..cameras import Camera
from ..io.config_files import unset
from .backgrounds import NAMED, default_background, evident_background
from .cache import cache_root
from .errors import DataError
from .images import box_downscaled, read_image_alpha, resized_size
from .parsed import BLENDER_LAYOUT, REGION_LABELS, ImageRecord, ParsedScene, ParseOptions
from .depth_maps import read_depth_map, warn_masked_depth
from .random_init import box_points, cube_points, frustum_points

Background = Literal["white", "black", "random"] | tuple[float, float, float] | None


@dataclass
class DataManagerConfig:
    """Which dataset to load and how."""

    # --data and --data-factor: eg-train's short flags for these two fields, shown once in --help.
    # Parse this config nested (as eg-train does): at the top level an alias is the field's own name.
    data: Annotated[str, tyro.conf.arg(aliases=("--data",))] = "builtin:default"
    """Dataset: builtin:NAME (tiny, default, farside, nearside, combined, *-large; dynamic,
    dynamic-tiny), a COLMAP folder (images/ + sparse/0), a transforms.json (or its folder), or a
    Neu3D / DyNeRF multi-view video folder (poses_bounds.npy + cam00.mp4 ...)."""
    data_factor: Annotated[int, tyro.conf.arg(aliases=("--data-factor",))] = 1
    """Downscale images by this integer factor (uses images_N/ when present, else caches a resize)."""
    test_every: int = 8
    """Every N-th image in name order is a test image (0: no test images). Ignored when the
    dataset has its own split and use_dataset_split is set."""
    use_dataset_split: bool = True
    """Use the dataset's own train/test lists (split.json, train_filenames, Blender files)."""
    eval_split: Literal["test", "val"] = "test"
    """Blender / D-NeRF folder: evaluate on transforms_test.json or transforms_val.json (training
    always uses transforms_train.json)."""
    seed: tyro.conf.Suppress[int] = 0
    """Seed of the training camera order and of random initial points. Not a flag: the pipeline
    sets it from the run's --seed, so one seed drives every random choice of a run."""
    normalize: bool = True
    """Translate and uniformly scale the scene so camera centres have mean 0 and max radius 1."""
    undistort: bool = True
    """Undistort images of distorted camera models with pycolmap into a cache (False: refuse them)."""
    background: Background = None
    """What transparent images are composited on and renders drawn over: white, black, three
    values in [0, 1], or random (a random colour behind each training view, the layout's colour
    for evaluation; needs images with alpha). Unset: the layout's convention, white for a
    Blender / D-NeRF folder, black otherwise; a Blender folder without alpha renders on the
    colour its images' borders evidently have."""
    n_random_points: int = 10_000
    """Random initial points when the dataset has no point cloud (or with random_init)."""
    random_init: bool = False
    """Ignore the dataset's points and start from random ones, as for a dataset without points
    (3DGS-MCMC's random-initialisation option)."""
    random_init_mode: Literal["frusta", "box", "cube"] | None = None
    """Where random initial points go: 'frusta', along the rays of random training pixels at
    log-uniform depths in random_init_depth, coloured by those pixels; 'box', uniform in the box
    of the camera centres and their focus point; 'cube', uniform in a cube around the focus point
    that every view sees (3DGS's synthetic recipe); both with random colours. Unset: cube for a
    Blender / D-NeRF folder, frusta otherwise (docs/data.md compares them)."""
    random_init_depth: tuple[float, float] = (0.1, 10.0)
    """Near and far depth of 'frusta' points, in units of the scene extent (camera spread)."""
    frame_stride: int = 1
    """Dynamic scenes: keep every this-many-th frame of each camera."""
    max_frames: Annotated[int | None, unset("all")] = None
    """Dynamic scenes: use the first this-many frames of each camera's clip."""
    cache_dir: Annotated[str | None, unset("$EXPLOREGS_CACHE, else $XDG_CACHE_HOME/exploregs or ~/.cache/exploregs")] = None
    """Cache root for built-in scenes and derived images."""
    cache_beside_data: bool = False
    """Keep derived images in DATASET/.exploregs/ (when writable) instead of the cache root; by
    default a dataset folder is never written to."""

    def setup(self) -> "DataManager":
        return DataManager(self)

    def parse_options(self) -> ParseOptions:
        if self.data_factor < 1:
            raise DataError("--data-factor", f"must be an integer >= 1, got {self.data_factor}")
        if self.test_every < 0:
            raise DataError("--test-every", f"must be >= 0, got {self.test_every}")
        if isinstance(self.background, str):
            if self.background not in (*NAMED, "random"):
                raise DataError("--background", f"must be white, black, random or three values in [0, 1], "
                                f"got {self.background!r}")
        elif self.background is not None and (
                len(self.background) != 3 or not all(0.0 <= c <= 1.0 for c in self.background)):
            raise DataError("--background", f"must be three values in [0, 1], got {self.background}")
        if self.eval_split not in ("test", "val"):
            raise DataError("--eval-split", f"must be test or val, got {self.eval_split!r}")
        if self.n_random_points < 1:
            raise DataError("--n-random-points", f"must be >= 1, got {self.n_random_points}")
        if self.frame_stride < 1:
            raise DataError("--frame-stride", f"must be >= 1, got {self.frame_stride}")
        if self.max_frames is not None and self.max_frames < 1:
            raise DataError("--max-frames", f"must be >= 1, got {self.max_frames}")
        near, far = self.random_init_depth
        if not 0.0 < near < far:
            raise DataError("--random-init-depth", f"needs 0 < near < far, got {near}, {far}")
        root = Path(self.cache_dir).expanduser() if self.cache_dir else cache_root()
        return ParseOptions(
            data_factor=self.data_factor,
            undistort=self.undistort,
            cache_root=root,
            cache_beside_data=self.cache_beside_data,
            background=self.background_colour(),
            frame_stride=self.frame_stride,
            max_frames=self.max_frames,
            eval_split=self.eval_split,
        )

    def background_colour(self) -> np.ndarray | None:
        """[3] float64 colour the option names, or None (unset or random: the layout's colour)."""
        if self.background is None or self.background == "random":
            return None
        colour = NAMED[self.background] if isinstance(self.background, str) else self.background
        return np.asarray(colour, dtype=np.float64)


def split_indices(names: list[str], test_every: int, split: dict[str, list[str]] | None) -> tuple[list[int], list[int]]:
    """(train, test) indices into ``names`` (sorted): the dataset's split, or every
    ``test_every``-th name (0, k, 2k, ...)."""
    if split is not None:
        index = {n: i for i, n in enumerate(names)}
        test = sorted(index[n] for n in split["test"])
        train = sorted(index[n] for n in split["train"])
        return train, test
    test = [i for i in range(len(names)) if test_every > 0 and i % test_every == 0]
    train = [i for i in range(len(names)) if test_every <= 0 or i % test_every != 0]
    return train, test


@dataclass
class _Item:
    camera: Camera
    image: Tensor  # uint8 [H, W, 3]
    depth: Tensor | None  # float32 [H, W, 1], normalised units
    labels: Tensor | None  # uint8 [H, W]
    alpha: Tensor | None = None  # uint8 [H, W, 1] for images with an alpha channel
    masks: dict[str, Tensor] | None = None  # bool [H, W] per region, made once from labels


class DataManager:
    """Holds the parsed dataset; see the contract in the project brief."""

    def __init__(self, config: DataManagerConfig) -> None:
        self.config = config
        options = config.parse_options()
        from .dataparser import parse_dataset  # the readers (pycolmap, the built-in scenes) load when used

        self.parsed: ParsedScene = parse_dataset(config.data, options, normalize=config.normalize)
        self.scene_name = self.parsed.name
        names = [im.name for im in self.parsed.images]
        split = self.parsed.split if config.use_dataset_split else None
        train_ids, test_ids = split_indices(names, config.test_every, split)
        if not train_ids:
            raise DataError(f"--data {config.data}", "no training images after the train/test split")
        if config.eval_split != "test" and self.parsed.layout != BLENDER_LAYOUT:
            raise DataError("--datamanager.eval-split", f"{config.eval_split} needs a Blender folder "
                            f"(transforms_train.json, transforms_{config.eval_split}.json); --data {config.data} is not one")
        # Transparent pixels go on the option's colour, else on the one the parser chose for the layout.
        background = options.background if options.background is not None else self.parsed.background
        if background is None:
            background = np.asarray(NAMED[default_background(self.parsed.layout)], dtype=np.float64)
        self._train_ids = train_ids
        self._masked_depth: dict[Path, tuple[int, int]] = {}  # depth file -> (non-finite pixels, pixels)
        self._train = [self._load(self.parsed.images[i], background) for i in train_ids]
        self._test = [self._load(self.parsed.images[i], background) for i in test_ids]
        warn_masked_depth(self._masked_depth)
        # Region masks: the labels every dataset has, and "moving" where a dynamic one marks it
        # (the scan stops at the first image that has a moving pixel).
        moving = REGION_LABELS["moving"]
        has_moving = any(bool((it.labels == moving).any()) for it in self._train + self._test if it.labels is not None)
        self.regions = {name: value for name, value in REGION_LABELS.items() if name != "moving" or has_moving}
        for item in self._train + self._test:
            self._add_masks(item)
        self.train_cameras: list[Camera] = [it.camera for it in self._train]
        self.test_cameras: list[Camera] = [it.camera for it in self._test]
        points, points_rgb = self.parsed.points, self.parsed.points_rgb
        if points is None or config.random_init:
            points, points_rgb = self._random_points()
        self.points: Tensor | None = _tensor(points)
        self.points_rgb: Tensor | None = _tensor(points_rgb)
        self.scene_extent: float = float(self.parsed.scene_extent)
        norm = self.parsed.normalization
        self.normalization: tuple[Tensor, float] = (
            torch.tensor(norm.translation, dtype=torch.float32), float(norm.scale))
        self.random_background: bool = config.background == "random"
        """Training views go on a random colour each step (the pipeline draws it); evaluation on ``background``."""
        self.background: Tensor = torch.tensor(self._render_background(background), dtype=torch.float32)
        self._generator = torch.Generator().manual_seed(config.seed)
        self._order: Tensor = torch.randperm(len(self._train), generator=self._generator, device="cpu")
        self._position = 0
        self._epoch = 0
        self._held: list[int] = []  # training indices kept out of the order (hold_out)
        self._coarse: dict[tuple[int, int], _Item] = {}  # (train index, downscale) -> its coarse level

    def _render_background(self, composited: np.ndarray) -> np.ndarray:
        """The colour renders are drawn over: the one transparent pixels were composited on, unless
        the images have no alpha. Then they are used as they are, and a Blender folder's images
        say by their borders which background they were flattened on: with the option unset,
        renders use that one (one line says so)."""
        if self.has_alpha:
            return composited
        if self.config.background == "random":
            path = next(self.parsed.images[i].path for i, it in zip(self._train_ids, self._train) if it.alpha is None)
            raise DataError(path, "--datamanager.background random needs images with an alpha channel, "
                            "and this one has none")
        if self.parsed.layout != BLENDER_LAYOUT:
            return composited
        evident, shares = evident_background([it.image.numpy() for it in self._train])
        listed = ", ".join(f"{name} {100 * share:.1f}%" for name, share in shares.items())
        if evident is None:
            seen = f"their borders have no one colour ({listed} of the border pixels)"
        else:
            seen = f"their background is evidently {evident} ({listed} of the border pixels)"
        if self.config.background is None and evident is not None:
            chosen, why = np.asarray(NAMED[evident], dtype=np.float64), f", so renders use {evident}"
        else:
            chosen = composited
            why = ("; renders use " + " ".join(f"{c:g}" for c in composited) +
                   (" as --datamanager.background says" if self.config.background is not None else ", the layout's default"))
        print(f"note: {self.parsed.root}: the images have no alpha channel and are used as they are; "
              f"{seen}{why}", flush=True)
        return chosen

    def _random_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Initial points for a dataset without them (or with random_init), seeded by the run."""
        config = self.config
        mode = config.random_init_mode or ("cube" if self.parsed.layout == BLENDER_LAYOUT else "frusta")
        if mode == "box":
            return box_points(self.parsed.images, config.n_random_points, config.seed)
        if mode == "cube":
            return cube_points([self.parsed.images[i] for i in self._train_ids], config.n_random_points, config.seed)
        near, far = (d * self.parsed.scene_extent for d in config.random_init_depth)
        views = [(it.camera.viewmat.numpy(), it.camera.K.numpy(), it.image.numpy()) for it in self._train]
        return frustum_points(views, config.n_random_points, near, far, config.seed)

    def _load(self, record: ImageRecord, background: np.ndarray) -> _Item:
        pixels, alpha = read_image_alpha(record.path, background)
        if pixels.shape[:2] != (record.height, record.width):
            raise DataError(record.path, f"image is {pixels.shape[1]}x{pixels.shape[0]}, expected "
                            f"{record.width}x{record.height}")
        camera = Camera(
            torch.tensor(record.viewmat, dtype=torch.float32),
            torch.tensor(record.K, dtype=torch.float32),
            record.width, record.height, record.name, record.time,
        )
        depth = labels = None
        size = (record.width, record.height)
        if record.depth_path is not None:
            depth_np, self._masked_depth[record.depth_path] = read_depth_map(record.depth_path, size)
            depth_np = depth_np * self.parsed.depth_scale
            depth = torch.from_numpy(depth_np.astype(np.float32))[..., None]
        if record.mask_path is not None:
            labels = torch.from_numpy(_load_labels(record.mask_path, size))
        alpha_t = torch.from_numpy(alpha) if alpha is not None else None
        return _Item(camera, torch.from_numpy(np.ascontiguousarray(pixels).copy()), depth, labels, alpha_t)

    @property
    def is_dynamic(self) -> bool:
        """The views are frames of a dynamic scene (their cameras carry times)."""
        return any(camera.time is not None for camera in self.train_cameras)

    def _add_masks(self, item: _Item) -> _Item:
        """Sets ``item.masks`` from its region labels, once per image (not per step: a comparison
        per region is an operator each time a view is drawn)."""
        if item.labels is not None:
            item.masks = {name: item.labels == value for name, value in self.regions.items()}
        return item

    def _item(self, item: _Item, device: torch.device | None = None) -> tuple[Camera, Tensor, dict[str, Any]]:
        image = item.image
        if device is not None and device.type == "cuda":
            # uint8 to the GPU, converted there: a quarter of the bytes, no float pass on the host,
            # and from pinned memory the copy is queued instead of waited for (the caching host
            # allocator keeps the pinned block until the copy is done)
            image = image.pin_memory().to(device, non_blocking=True)
        elif device is not None and image.device != device:
            image = image.to(device)
        extras: dict[str, Any] = {}
        if item.depth is not None:
            extras["depth"] = item.depth
        if item.masks is not None:
            extras["masks"] = item.masks
        if item.alpha is not None:
            extras["alpha"] = item.alpha / 255.0
        # uint8 / 255.0 divides in float32 (the default dtype) with no separate conversion
        return item.camera, image / 255.0, extras

    @property
    def has_alpha(self) -> bool:
        """Every training image has an alpha channel (extras["alpha"] [H, W, 1] in [0, 1])."""
        return all(item.alpha is not None for item in self._train)

    def train_item(self, index: int, device: torch.device | None = None,
                   downscale: int = 1) -> tuple[Camera, Tensor, dict[str, Any]]:
        """(camera, image [H, W, 3] float32 in [0, 1], extras) of training image ``index``; the
        image on ``device`` when given (converted there from the stored uint8), else on the host.
        ``downscale`` > 1: the view of a coarse-to-fine level, its image, alpha, depth and masks
        ``downscale`` times smaller per side (see :meth:`_downscaled`)."""
        if downscale == 1:
            return self._item(self._train[index], device)
        key = (index, downscale)
        if key not in self._coarse:
            self._coarse[key] = self._add_masks(_downscaled(self._train[index], downscale))
        return self._item(self._coarse[key], device)

    def test_item(self, index: int, device: torch.device | None = None) -> tuple[Camera, Tensor, dict[str, Any]]:
        """(camera, image [H, W, 3] float32 in [0, 1], extras) of test image ``index``; the image on
        ``device`` when given, as :meth:`train_item`."""
        return self._item(self._test[index], device)

    def next_train(self) -> tuple[int, Camera, Tensor, dict[str, Any]]:
        """The next training image in a seeded random order; a fresh permutation each epoch."""
        index = self.next_train_indices(1)[0]
        return (index, *self.train_item(index))

    def next_train_indices(self, count: int) -> list[int]:
        """The next ``count`` training indices of the seeded order (a fresh permutation each
        epoch), passing over held-out ones (:meth:`hold_out`). Every rank of a data-parallel run
        draws the whole global batch this way, so the ranks agree on it, and loads only its own
        share with :meth:`train_item`."""
        indices = []
        while len(indices) < count:
            if self._position >= len(self._order):
                self._order = torch.randperm(len(self._train), generator=self._generator, device="cpu")
                self._position = 0
                self._epoch += 1
            index = int(self._order[self._position])
            self._position += 1
            if index not in self._held:
                indices.append(index)
        return indices

    def last_epoch_draws(self, count: int, draws_left: int) -> list[bool]:
        """For each of the next ``count`` draws of :meth:`next_train_indices`, whether it belongs to
        the last epoch of the order that the run's ``draws_left`` remaining draws complete
        (:func:`in_last_epoch`). None of them while views are held out: the order then passes over
        some of its places, and an epoch's draws are not every view."""
        if self._held:
            return [False] * count
        return in_last_epoch(self._position, len(self._train), draws_left, count)

    def hold_out(self, indices: list[int]) -> None:
        """Keep these training views out of the order until :meth:`return_held` (a count rule
        scores them); at least one view stays in training."""
        if any(not 0 <= i < len(self._train) for i in indices) or len(set(indices)) >= len(self._train):
            raise ValueError(f"hold_out: {indices} must be distinct training indices, fewer than "
                             f"{len(self._train)}")
        self._held = sorted(set(int(i) for i in indices))

    def return_held(self) -> None:
        """The held-out views take part in training again (from the next draw of the order)."""
        self._held = []

    @property
    def held_out(self) -> list[int]:
        """Training indices currently held out of training (:meth:`hold_out`)."""
        return list(self._held)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the same camera order after a resume."""
        return {
            "order": self._order.clone(),
            "position": self._position,
            "epoch": self._epoch,
            "generator": self._generator.get_state(),
            "train_names": [c.name for c in self.train_cameras],
            "held_out": list(self._held),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        names = [c.name for c in self.train_cameras]
        if list(state["train_names"]) != names:
            raise DataError("data manager state", "the checkpoint was made with different training images")
        order = torch.as_tensor(state["order"], dtype=torch.int64)
        if sorted(order.tolist()) != list(range(len(names))) or not 0 <= int(state["position"]) <= len(names):
            raise DataError("data manager state", "camera order does not match the training images")
        self._order = order.clone()
        self._position = int(state["position"])
        self._epoch = int(state["epoch"])
        self._generator.set_state(state["generator"])
        held = [int(i) for i in state.get("held_out", [])]  # a checkpoint from before hold_out held none
        if held:
            self.hold_out(held)
        else:
            self.return_held()

    @property
    def epoch(self) -> int:
        return self._epoch


def in_last_epoch(position: int, length: int, draws_left: int, count: int) -> list[bool]:
    """For each of the next ``count`` draws of an order that deals ``length`` views per epoch, of
    which ``position`` are dealt in the current one (``length``: all, the next draw begins a new
    epoch), whether it belongs to the last epoch that the run's ``draws_left`` draws (these
    included) complete. A draw is the ``taken``-th of its epoch; its epoch completes when the
    ``length - taken`` draws it still needs fit in the ``after`` draws that follow, and is the last
    to when the next one's ``length`` do not:

        length - taken <= after < 2 length - taken.

    Both sides move by one per draw, so the answer is the same for every draw of an epoch: the
    draws marked are one whole epoch, each view once, or none where the run completes no epoch."""
    if length <= 0:
        return [False] * count
    marked = []
    for j in range(count):
        taken = (position + j) % length + 1
        after = draws_left - j - 1
        marked.append(length - taken <= after < 2 * length - taken)
    return marked


def _downscaled(item: _Item, factor: int) -> _Item:
    """``item`` at 1/``factor`` of its size per side, as --data-factor makes it: the image and
    alpha area-filtered (:func:`box_downscaled`), depth and region labels nearest, and the camera
    by :meth:`Camera.scaled`, which scales K's rows by the exact size ratio: with pixel centres at
    +0.5, a box of ``factor`` pixels [f j, f (j + 1)) has its centre f (j + 0.5), i.e. pixel j + 0.5
    of the small image, so u' = u / f maps centres to centres with no offset."""
    size = resized_size(item.camera.width, item.camera.height, factor)
    width, height = size
    small = item.camera.scaled(1.0 / factor, size)

    def nearest(array: Tensor) -> Tensor:
        mode = "F" if array.dtype == torch.float32 else "L"
        image = Image.fromarray(np.ascontiguousarray(array.numpy().reshape(array.shape[0], array.shape[1])), mode)
        out = torch.from_numpy(np.asarray(image.resize(size, Image.Resampling.NEAREST)).copy())
        return out.reshape(height, width, *array.shape[2:])

    return _Item(
        small,
        torch.from_numpy(box_downscaled(item.image.numpy(), size)),
        None if item.depth is None else nearest(item.depth),
        None if item.labels is None else nearest(item.labels),
        None if item.alpha is None else torch.from_numpy(box_downscaled(item.alpha.numpy(), size)),
    )


def _tensor(array: np.ndarray | None) -> Tensor | None:
    return None if array is None else torch.tensor(array, dtype=torch.float32)


def _load_labels(path: Path, size: tuple[int, int]) -> np.ndarray:
    """uint8 [H, W] region labels resized (nearest) to ``size`` = (width, height)."""
    try:
        with Image.open(path) as im:
            if im.size != size:
                im = im.resize(size, Image.Resampling.NEAREST)
            labels = np.asarray(im, dtype=np.uint8)
    except OSError as err:
        raise DataError(path, f"mask file is unreadable ({err})") from err
    if labels.ndim != 2 or labels.max(initial=0) > max(REGION_LABELS.values()):
        raise DataError(path, "mask must be a single-channel image of region labels " +
                        ", ".join(f"{v} ({k})" for k, v in REGION_LABELS.items()))
    return labels.copy()
