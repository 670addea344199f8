"""LPIPS perceptual distance (Zhang et al. 2018, v0.1) with the AlexNet or VGG16 backbone.

The evaluation's LPIPS column (Section 4.2) and the LPIPS term of the loss (Eq. 15). The backbone
is rebuilt in plain torch with torchvision's layer layout, so torchvision's checkpoint
(`alexnet-owt-7be5be79.pth` / `vgg16-397923af.pth`) and the lpips package's linear layers
(`alex.pth` / `vgg.pth`) load by their original keys. `weights="random"` builds the same network from a seed
instead (no file read): its distances mean nothing, but it costs what the pretrained one costs, for timing
the loss term where the weights are absent.

`LPIPS.forward` is the float32 reference: the evaluation scores with it, and its parity tests hold to it. The
evaluation may run the backbone in float16 or bfloat16 and channels-last instead (`precision`, `channels_last`;
pig.metrics.precision), each tap read in that arithmetic by a distance computed in float32.
`TrainingLPIPS` wraps it for the loss with the speed levers of the fit (bf16 backbone and head, compiled).
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import torch
import torch.nn as nn

from pig.metrics.precision import check_precision, network_arithmetic
from pig.metrics.weights import (
    LPIPS_LINEAR_FILES,
    TORCHVISION_FILES,
    WeightsMissing,
    load_state_dict,
    locate,
    lpips_package_weights,
)

__all__ = ["LPIPS", "TrainingLPIPS", "WeightsMissing", "backbone_features", "head"]

# Input normalisation of the lpips package's ScalingLayer (for inputs in [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# Indices into `features` after which LPIPS taps the activations (after each ReLU it compares).
TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}
CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}
# Smallest image side whose deepest tap still has a pixel (AlexNet's stride-4 conv and two pools; VGG's 4 pools).
MIN_SIDE = {"alex": 31, "vgg": 16}


def backbone_features(net: str) -> nn.Sequential:
    """torchvision's `alexnet().features` / `vgg16().features` layer stack (same indices, untrained)."""
    if net == "alex":
        return nn.Sequential(
            nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(),
            nn.MaxPool2d(3, stride=2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),
            nn.MaxPool2d(3, stride=2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
            nn.MaxPool2d(3, stride=2),
        )
    if net == "vgg":
        layers: list[nn.Module] = []
        channels = 3
        for width in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
            if width == "M":
                layers.append(nn.MaxPool2d(2, stride=2))
            else:
                layers += [nn.Conv2d(channels, width, 3, padding=1), nn.ReLU()]
                channels = width
        return nn.Sequential(*layers)
    raise ValueError(f"LPIPS backbone must be 'alex' or 'vgg', found {net!r}")


class LPIPS(nn.Module):
    """Frozen LPIPS network; `forward(x, y)` on (B, 3, H, W) images in [0, 1] -> (B,) distances.

    Differentiable w.r.t. the images. Raises `WeightsMissing` when either weight file is absent;
    `backbone_weights` / `linear_weights` name the files directly, otherwise they are looked up
    in the torch hub cache (and the lpips package folder for the linear layers). `weights="random"` looks up
    nothing and initialises both from `seed` (see `_initialise`). `precision` (float32, float16, bfloat16): the
    arithmetic of the backbone (autocast), its taps kept in it and the distance in float32; `channels_last`: the
    backbone's weights and inputs in channels-last memory format.
    """

    def __init__(self, net: str = "alex", backbone_weights: str | Path | None = None, linear_weights: str | Path | None = None,
                 weights: Literal["pretrained", "random"] = "pretrained", seed: int = 0, precision: str = "float32",
                 channels_last: bool = False):
        super().__init__()
        if weights not in ("pretrained", "random"):
            raise ValueError(f"LPIPS weights must be 'pretrained' or 'random', found {weights!r}")
        self.net = net
        self.precision, self.channels_last = check_precision(precision, "LPIPS"), channels_last
        self.features = backbone_features(net)
        self.taps = TAPS[net]
        self.field, self.stride = receptive_field(self.features, self.taps[-1])
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS[net])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

        if weights == "random":
            self._initialise(torch.Generator().manual_seed(seed))
        else:
            backbone_path = locate(TORCHVISION_FILES[net], backbone_weights, [], f"LPIPS {net} backbone")
            linear_path = locate(LPIPS_LINEAR_FILES[net], linear_weights, [lpips_package_weights()], f"LPIPS {net} linear layers")
            self._load_backbone(backbone_path)
            self._load_linear(linear_path)
        if channels_last:
            self.features.to(memory_format=torch.channels_last)
        self.requires_grad_(False)
        self.eval()

    @torch.no_grad()
    def _initialise(self, generator: torch.Generator) -> None:
        """He-normal convolutions with zero biases (activations keep their scale through the ReLUs) and
        linear weights uniform in [0, 2/C) (non-negative, as LPIPS clamps its learnt ones; mean 1/C per
        channel), all drawn from `generator` alone: the seed fixes them, whatever the global RNG's state."""
        for layer in self.features:
            if isinstance(layer, nn.Conv2d):
                nn.init.kaiming_normal_(layer.weight, nonlinearity="relu", generator=generator)
                layer.bias.zero_()
        for lin in self.lins:
            lin.weight.copy_(torch.rand(lin.weight.shape, generator=generator) * (2 / lin.in_channels))

    def _load_backbone(self, path: Path) -> None:
        state = load_state_dict(path)
        wanted = {k: v for k, v in state.items() if k.startswith("features.")}
        expected = {f"features.{k}" for k in self.features.state_dict()}
        if set(wanted) != expected:
            raise WeightsMissing(f"{path}: expected torchvision {self.net} keys {sorted(expected)}, found {sorted(wanted)}")
        self.features.load_state_dict({k.removeprefix("features."): v for k, v in wanted.items()})

    def _load_linear(self, path: Path) -> None:
        state = load_state_dict(path)
        # The lpips package names its 1x1 convolutions lin{k}.model.1.weight (after a Dropout).
        expected = {f"lin{k}.model.1.weight" for k in range(len(self.lins))}
        if not expected <= set(state):
            raise WeightsMissing(f"{path}: expected lpips linear-layer keys {sorted(expected)}, found {sorted(state)}")
        for k, lin in enumerate(self.lins):
            lin.weight.data.copy_(state[f"lin{k}.model.1.weight"])

    def _activations(self, images: torch.Tensor) -> list[torch.Tensor]:
        h = ((2 * images - 1) - self.shift) / self.scale
        if self.channels_last:
            h = h.contiguous(memory_format=torch.channels_last)
        # A float16 or bfloat16 tap stays so: `_channel_norm` sums its squares in float32 (in float16 the sum over
        # up to 512 channels would overflow) and the quotients are float32, read off the tap without a widened copy.
        taps = []
        with network_arithmetic(h.device.type, self.precision):
            for index, layer in enumerate(self.features):
                h = layer(h)
                if index in self.taps:
                    taps.append(h)
                    if len(taps) == len(self.taps):
                        break
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The reference path: (B,) distances in float32 (outside autocast); its name and signature stay."""
        self._check(x, y)
        return self.distance(x, self.reference(y))

    def reference(self, y: torch.Tensor) -> list[torch.Tensor]:
        """The unit-normalised taps of images `y`, for `distance`: the evaluation scores every LOD's renders
        against one pass over the ground truth."""
        return [_unit(fy) for fy in self._activations(y)]

    def distance(self, x: torch.Tensor, reference: list[torch.Tensor], frame: tuple[int, int] | None = None) -> torch.Tensor:
        """(B,) distances of images `x` to the images whose `reference` taps are given; equals forward(x, y).

        `frame` (height, width): `x` and the reference are the `window` of frames of that size outside which the
        compared images are equal; each tap's spatial mean is then taken over the whole frame's tap."""
        if reference and x.shape[0] != reference[0].shape[0]:
            raise ValueError(f"LPIPS: {x.shape[0]} images against a reference of {reference[0].shape[0]}")
        self._check(x, x)
        counts = [h * w for h, w in self.tap_sizes(*frame)] if frame is not None else None
        total = x.new_zeros(x.shape[0])
        for k, (fx, ny, lin) in enumerate(zip(self._activations(x), reference, self.lins)):
            if fx.shape != ny.shape:
                raise ValueError(f"LPIPS: images of {tuple(x.shape)} against reference taps of {tuple(ny.shape)}")
            # Weight the squared difference of the unit features, average spatially; the difference in one pass
            # over the tap (ny - fx / |fx|).
            term = lin(torch.addcdiv(ny, fx, _channel_norm(fx), value=-1).square())
            total = total + (term.mean(dim=(1, 2, 3)) if counts is None else term.sum(dim=(1, 2, 3)) / counts[k])
        return total

    def tap_sizes(self, height: int, width: int) -> list[tuple[int, int]]:
        """(h, w) of each tap of a (height, width) image, by the layers' size arithmetic."""
        sizes, size = [], (height, width)
        for index, layer in enumerate(self.features[:self.taps[-1] + 1]):
            if isinstance(layer, (nn.Conv2d, nn.MaxPool2d)):
                k, s, p = (_pair(getattr(layer, name)) for name in ("kernel_size", "stride", "padding"))
                size = tuple((n + 2 * p[d] - k[d]) // s[d] + 1 for d, n in enumerate(size))
            if index in self.taps:
                sizes.append(size)
        return sizes

    def window(self, box: tuple[int, int, int, int], height: int, width: int) -> tuple[slice, slice]:
        """The rows and columns of (height, width) frames that decide the distance of two images equal outside
        `box` (top, bottom, left, right; half-open): the box grown by the backbone's receptive field and one stride
        (a tap unit whose field reaches past the window sees no difference, in the window as in the frame, so its
        term is zero either way), its start on the stride's grid so that the window's taps are the frame's.
        `distance(x[..., rows, cols], reference of y[..., rows, cols], frame=(height, width))` is then
        `forward(x, y)` up to the order of the sums."""
        margin = self.field + self.stride
        top, bottom, left, right = box
        top, left = (max(0, start - margin) // self.stride * self.stride for start in (top, left))
        bottom, right = min(height, bottom + margin), min(width, right + margin)
        if min(bottom - top, right - left) < MIN_SIDE[self.net]:  # a frame too small to cut
            return slice(0, height), slice(0, width)
        return slice(top, bottom), slice(left, right)

    def _check(self, x: torch.Tensor, y: torch.Tensor) -> None:
        if x.shape != y.shape or x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS expects two (B, 3, H, W) tensors of one shape, found {tuple(x.shape)} and {tuple(y.shape)}")
        if min(x.shape[2:]) < MIN_SIDE[self.net]:
            raise ValueError(f"LPIPS ({self.net}) needs images of at least {MIN_SIDE[self.net]} pixels per side, "
                             f"found {x.shape[3]}x{x.shape[2]}")


def receptive_field(features: nn.Sequential, last: int) -> tuple[int, int]:
    """(receptive field in pixels, stride) of layer `last` of a stack of square convolutions, pools and pointwise
    layers."""
    field, stride = 1, 1
    for layer in features[:last + 1]:
        if isinstance(layer, (nn.Conv2d, nn.MaxPool2d)):
            field += (_pair(layer.kernel_size)[0] - 1) * stride
            stride *= _pair(layer.stride)[0]
    return field, stride


def _pair(value: int | tuple[int, ...]) -> tuple[int, ...]:
    return value if isinstance(value, tuple) else (value, value)


def _channel_norm(features: torch.Tensor) -> torch.Tensor:
    """(B, 1, h, w) Euclidean norm along channels plus the lpips package's eps, in float32 or wider."""
    if features.dtype in (torch.float16, torch.bfloat16):
        # Read as it is (a CUDA reduction casts as it reads), not copied wider first.
        return torch.linalg.vector_norm(features, dim=1, keepdim=True, dtype=torch.float32) + 1e-10
    # The lpips package's form: with vector_norm a CPU's reference taps took 1.6x as long (benchmarks/NOTES.md).
    return features.pow(2).sum(1, keepdim=True).sqrt() + 1e-10


def _unit(features: torch.Tensor) -> torch.Tensor:
    """Features unit-normalised along channels (eps as the lpips package), in float32 or wider."""
    return features / _channel_norm(features)


def head(fx: torch.Tensor, fy: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """One tap's term of LPIPS in the features' own dtype, autocast off: (B, C, h, w) pairs and the (1, C, 1, 1)
    linear weight -> (B,) in float32 or wider. In bf16 the normalised features and their difference stay bf16 (under autocast
    `pow` and `sum` would make them float32 tensors of the tap's full size); the spatial mean is taken in float32."""
    with torch.autocast(fx.device.type, enabled=False):
        nx = fx / (fx.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        ny = fy / (fy.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        d = ((nx - ny).pow(2) * weight.to(fx.dtype)).sum(1)
        return d.to(torch.promote_types(d.dtype, torch.float32)).mean(dim=(1, 2))


class TrainingLPIPS(nn.Module):
    """`net` (an LPIPS) as the loss of Eq. 15 computes it: (B, 3, H, W) pairs in [0, 1] -> (B,) float32 (float64
    for float64 inputs and network).

    `bf16`: the backbone under bf16 autocast (float32 weights). `bf16_head`: inputs channels-last and `head` in the
    features' bf16, not the reference's float32 normalisation. `compiled`: torch.compile of the whole (static
    shapes: one graph per input shape), in `mode`. All off, this is `net.forward`.
    """

    def __init__(self, net: LPIPS, bf16: bool = False, bf16_head: bool = False, compiled: bool = False,
                 mode: str = "default"):
        super().__init__()
        self.net, self.bf16, self.bf16_head = net, bf16, bf16_head
        self._distance = torch.compile(self._eager, dynamic=False, mode=mode) if compiled else self._eager

    def _eager(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x.device.type, torch.bfloat16, enabled=self.bf16):
            if not self.bf16_head:
                d = self.net(x, y)
                return d.to(torch.promote_types(d.dtype, torch.float32))
            self.net._check(x, y)
            x, y = (t.contiguous(memory_format=torch.channels_last) for t in (x, y))
            taps = zip(self.net._activations(x), self.net._activations(y), self.net.lins)
        return sum(head(fx, fy, lin.weight.view(1, -1, 1, 1)) for fx, fy, lin in taps)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self._distance(x, y)
