"""The deformation field of dynamic scenes (4DGS, Wu et al. CVPR 2024), as pure functions and
two small modules: HexPlane features over (x, y, z, t) and an MLP decoder of offsets.

A canonical Gaussian at ``q = (x, y, z, t)`` (space normalised to the field's box, time to
[-1, 1]) reads one feature vector per resolution level ``l`` from six planes, one per pair of
coordinates, and multiplies them (the Hadamard product of HexPlane / K-planes)::

    f_l(q) = prod_{(a, b)} bilinear(P_l^{ab}, q_a, q_b)        [C]
    f(q)   = concat_l f_l(q)                                    [C L]

The three space-time planes (xt, yt, zt) start at 1 and the three space planes at U(0.1, 0.5),
so at the start the features do not depend on time. The decoder maps ``f`` to offsets of the
canonical parameters::

    means(t) = means + dx,   quats(t) = quats + dq,   log scales(t) = log scales + ds

Its last layers start at zero, so switching the deformation on after the static warm-up leaves
the rendered scene unchanged and training continues smoothly from there.
"""

from __future__ import annotations

import itertools
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

PLANE_PAIRS: tuple[tuple[int, int], ...] = tuple(itertools.combinations(range(4), 2))
"""Coordinate pairs of the six planes: xy, xz, xt, yz, yt, zt (coordinates 0..3 = x, y, z, t)."""
SPACE_PLANES = tuple(i for i, pair in enumerate(PLANE_PAIRS) if 3 not in pair)
"""Indices of the xy, xz and yz planes."""
TIME_PLANES = tuple(i for i, pair in enumerate(PLANE_PAIRS) if 3 in pair)
"""Indices of the xt, yt and zt planes."""
SPACE_INIT = (0.1, 0.5)
"""Space planes start uniform in this range (4DGS, K-planes)."""
BOX_MIN_SIZE = 1e-6
"""Smallest side of the field's box (a flat or single-point cloud would divide by zero)."""


def plane_shape(pair: tuple[int, int], resolution: tuple[int, int, int, int]) -> tuple[int, int]:
    """(rows, columns) of the plane over coordinates ``pair`` = (a, b): rows index b, columns a,
    so that grid_sample's (x, y) sample point is (q_a, q_b)."""
    a, b = pair
    return resolution[b], resolution[a]


def sample_plane(plane: Tensor, coords: Tensor) -> Tensor:
    """Bilinear features of a plane at points. plane: [C, R_b, R_a]; coords: [N, 2] in [-1, 1]
    (q_a, q_b) -> [N, C]. Outside [-1, 1] the border value is used (grid_sample's 'border')."""
    grid = coords.reshape(1, 1, -1, 2).to(plane.dtype)
    out = F.grid_sample(plane.unsqueeze(0), grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0, :, 0, :].transpose(0, 1)


def hexplane_features(levels: list[list[Tensor]], q: Tensor) -> Tensor:
    """HexPlane features. levels: per level, the six planes [C, R_b, R_a] of PLANE_PAIRS;
    q: [N, 4] normalised (x, y, z, t) -> [N, C * len(levels)]."""
    out = []
    for planes in levels:
        feature = None
        for plane, (a, b) in zip(planes, PLANE_PAIRS):
            value = sample_plane(plane, q[:, [a, b]])
            feature = value if feature is None else feature * value
        out.append(feature)
    return torch.cat(out, dim=-1)


def plane_tv(plane: Tensor) -> Tensor:
    """Total variation of a plane [C, H, W]: mean squared difference of neighbours along both axes."""
    dh = plane[:, 1:, :] - plane[:, :-1, :]
    dw = plane[:, :, 1:] - plane[:, :, :-1]
    return dh.square().mean() + dw.square().mean()


def time_smoothness(plane: Tensor) -> Tensor:
    """Mean squared second difference along the time axis (the rows) of a space-time plane
    [C, T, R]: penalises acceleration, so motion is smooth in time (K-planes, 4DGS)."""
    if plane.shape[1] < 3:
        return plane.new_zeros(())
    second = plane[:, 2:, :] - 2.0 * plane[:, 1:-1, :] + plane[:, :-2, :]
    return second.square().mean()


def static_l1(plane: Tensor) -> Tensor:
    """Mean |1 - P| of a space-time plane: pulls it back to 1, i.e. towards no motion."""
    return (1.0 - plane).abs().mean()


class HexPlaneField(nn.Module):
    """Multi-resolution HexPlane features. resolution: (x, y, z, t) cells at level 1; level ``m``
    multiplies the three space resolutions by ``m`` and keeps the time resolution (4DGS)."""

    def __init__(self, resolution: tuple[int, int, int, int], multires: tuple[int, ...], features: int,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        if len(resolution) != 4 or min(resolution) < 2:
            raise ValueError(f"resolution must be four sizes >= 2 (x, y, z, t), got {resolution}")
        if not multires or min(multires) < 1:
            raise ValueError(f"multires must be one or more factors >= 1, got {multires}")
        if features < 1:
            raise ValueError(f"features must be >= 1, got {features}")
        self.features = features
        self.levels = nn.ModuleList()
        for factor in multires:
            level_res = (resolution[0] * factor, resolution[1] * factor, resolution[2] * factor, resolution[3])
            planes = nn.ParameterList()
            for index, pair in enumerate(PLANE_PAIRS):
                shape = (features, *plane_shape(pair, level_res))
                if index in TIME_PLANES:
                    value = torch.ones(shape)
                else:
                    low, high = SPACE_INIT
                    value = torch.rand(shape, generator=generator) * (high - low) + low
                planes.append(nn.Parameter(value))
            self.levels.append(planes)

    @property
    def out_features(self) -> int:
        return self.features * len(self.levels)

    def planes(self) -> list[list[Tensor]]:
        return [list(level) for level in self.levels]

    def forward(self, q: Tensor) -> Tensor:
        """q: [N, 4] normalised (x, y, z, t) -> [N, out_features]."""
        return hexplane_features(self.planes(), q)


def _linear(n_in: int, n_out: int, generator: torch.Generator | None) -> nn.Linear:
    """A linear layer with PyTorch's default initialisation, U(-1/sqrt(n_in), 1/sqrt(n_in)) for
    weights and biases, drawn from ``generator`` so that a run's seed decides it."""
    layer = nn.utils.skip_init(nn.Linear, n_in, n_out)  # no draw from the global generator
    bound = 1.0 / math.sqrt(n_in)
    with torch.no_grad():
        for p in (layer.weight, layer.bias):
            p.copy_(torch.rand(p.shape, generator=generator) * (2 * bound) - bound)
    return layer


def _head(width: int, out: int, generator: torch.Generator | None) -> nn.Sequential:
    last = nn.utils.skip_init(nn.Linear, width, out)
    nn.init.zeros_(last.weight)  # the deformation starts as the identity (see the module doc)
    nn.init.zeros_(last.bias)
    return nn.Sequential(nn.ReLU(), _linear(width, width, generator), nn.ReLU(), last)


class DeformationDecoder(nn.Module):
    """features [N, F] -> (dx [N, 3], dq [N, 4], ds [N, 3]): a shared trunk of ``depth`` layers of
    ``width`` units and one head per offset, as in 4DGS."""

    def __init__(self, in_features: int, width: int, depth: int, generator: torch.Generator | None = None) -> None:
        super().__init__()
        if width < 1 or depth < 1:
            raise ValueError(f"width and depth must be >= 1, got {width}, {depth}")
        layers: list[nn.Module] = [_linear(in_features, width, generator)]
        for _ in range(depth - 1):
            layers += [nn.ReLU(), _linear(width, width, generator)]
        self.trunk = nn.Sequential(*layers)
        self.position = _head(width, 3, generator)
        self.rotation = _head(width, 4, generator)
        self.scale = _head(width, 3, generator)

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        hidden = self.trunk(features)
        return self.position(hidden), self.rotation(hidden), self.scale(hidden)


class DeformationField(nn.Module):
    """HexPlane + decoder over a box of the scene; ``active`` (saved with the state) says whether
    the static warm-up is over."""

    def __init__(self, box_min: Tensor, box_max: Tensor, resolution: tuple[int, int, int, int],
                 multires: tuple[int, ...], features: int, width: int, depth: int,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        size = (box_max - box_min).clamp_min(BOX_MIN_SIZE)
        self.register_buffer("box_min", box_min.detach().clone().float())
        self.register_buffer("box_size", size.detach().clone().float())
        self.register_buffer("active", torch.zeros((), dtype=torch.bool))
        self.grid = HexPlaneField(resolution, multires, features, generator)
        self.decoder = DeformationDecoder(self.grid.out_features, width, depth, generator)

    def normalized_coords(self, means: Tensor, time: float) -> Tensor:
        """means: [N, 3] world, time in [0, 1] -> q [N, 4] with space and time in [-1, 1]."""
        space = 2.0 * (means - self.box_min) / self.box_size - 1.0
        t = torch.full_like(means[:, :1], 2.0 * float(time) - 1.0)
        return torch.cat([space, t], dim=1)

    def forward(self, means: Tensor, time: float) -> tuple[Tensor, Tensor, Tensor]:
        """Offsets (dx [N, 3], dq [N, 4], ds [N, 3]) of Gaussians at canonical ``means`` [N, 3]."""
        return self.decoder(self.grid(self.normalized_coords(means, time)))

    def grid_parameters(self) -> list[nn.Parameter]:
        return list(self.grid.parameters())

    def mlp_parameters(self) -> list[nn.Parameter]:
        return list(self.decoder.parameters())


def robust_box(points: Tensor, trim_percent: float, margin: float) -> tuple[Tensor, Tensor]:
    """(min [3], max [3]) of ``points`` [P, 3] between the ``trim_percent`` and 100 - trim_percent
    percentiles per axis, enlarged by ``margin`` of its size on each side: stray far points (sky,
    noisy triangulations) would otherwise stretch the grid over empty space. Points outside read
    the border cells."""
    if points.numel() == 0:
        raise ValueError("the deformation field needs points to place its box, and got none")
    q = torch.tensor([trim_percent / 100.0, 1.0 - trim_percent / 100.0], dtype=points.dtype, device=points.device)
    low, high = torch.quantile(points, q, dim=0)
    pad = (high - low).clamp_min(BOX_MIN_SIZE) * margin
    return low - pad, high + pad

