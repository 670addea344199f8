"""GPU micro-benchmark of the parts of a fit iteration at the paper's sizes, each in the alternatives a speed lever picks from.

Times forward + backward (median of --repeats after --warmup) of: the two 5 x 512 decoders over 5 timesteps x
100k anchors in float32, TF32 and bf16 autocast (and compiled); the SSIM of 4 x 1330 x 1150 images with the
grouped depthwise convolution, a single-channel convolution and shifted sums (eager and compiled); the anchor
CG solve (100k anchors, KNN graph, lambda 8) with a residual check every 1 / 8 / 32 iterations; gsplat with
one call per timestep against one batched call; Adam steps (this package's, torch foreach, torch fused); and
the LPIPS-VGG term (random weights) in float32 and bf16. Prints one table. Run on the GPU machine:

    bash .gpu/device-setup.sh && export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text && \
        python3 benchmarks/fit_kernels_gpu.py
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from pig.avatar.decoders import AnchorDecoder
from pig.avatar.losses import boundary_band
from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import CGSystem
from pig.field.optim import Adam
from pig.metrics.ssim import ssim

ROWS: list[tuple[str, str, float, str]] = []


def timed(group: str, name: str, fn: Callable[[], object], warmup: int, repeats: int, note: str = "") -> float:
    try:
        for _ in range(warmup):
            fn()
        torch.cuda.synchronize()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        ms = 1000 * statistics.median(times)
    except Exception as err:  # one failing alternative must not hide the others' numbers
        ms = float("nan")
        note = f"failed: {type(err).__name__}: {str(err).splitlines()[0][:120]}"
    ROWS.append((group, name, ms, note))
    print(f"{group:10s} {name:40s} {ms:9.2f} ms {note}", flush=True)
    return ms


def decoders(args) -> None:
    torch.manual_seed(0)
    decoder = AnchorDecoder(16 + 2 * 4 + 1, 512, 5, 3).cuda()
    y = torch.randn(5, 100_000, 25, device="cuda")

    def step(module, autocast: bool):
        def run():
            with torch.autocast("cuda", torch.bfloat16, enabled=autocast):
                out = module(y)
            loss = sum(t.float().square().mean() for t in (out.offset, out.rotation, out.scale, out.opacity, out.sh))
            loss.backward()
        return run

    timed("decoders", "float32", step(decoder, False), args.warmup, args.repeats)
    torch.backends.cuda.matmul.allow_tf32 = True
    timed("decoders", "tf32", step(decoder, False), args.warmup, args.repeats)
    torch.backends.cuda.matmul.allow_tf32 = False
    timed("decoders", "bf16 autocast", step(decoder, True), args.warmup, args.repeats)
    compiled = torch.compile(decoder)
    timed("decoders", "bf16 autocast + compile", step(compiled, True), args.warmup + 2, args.repeats)


def shifted_blur(images: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    size = taps.numel()
    h, w = images.shape[-2:]
    rows = sum(taps[i] * images[..., i:h - size + 1 + i, :] for i in range(size))
    return sum(taps[i] * rows[..., i:w - size + 1 + i] for i in range(size))


def ssim_shift(x, y):
    from pig.metrics.ssim import K1, K2, gaussian_window
    taps = gaussian_window(x.dtype, x.device)
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    mu_x, mu_y, xx, yy, xy = shifted_blur(stacked, taps).chunk(5, dim=1)
    c1, c2 = K1 ** 2, K2 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * (xy - mu_x * mu_y) + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (xx - mu_x * mu_x + yy - mu_y * mu_y + c2)
    return (num / den).mean()


def ssim_single_channel(x, y):
    from pig.metrics.ssim import K1, K2, gaussian_window
    taps = gaussian_window(x.dtype, x.device)
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    b, c, h, w = stacked.shape
    flat = stacked.reshape(b * c, 1, h, w)
    blurred = F.conv2d(F.conv2d(flat, taps.view(1, 1, -1, 1)), taps.view(1, 1, 1, -1)).reshape(b, c, h - 10, w - 10)
    mu_x, mu_y, xx, yy, xy = blurred.chunk(5, dim=1)
    c1, c2 = K1 ** 2, K2 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * (xy - mu_x * mu_y) + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (xx - mu_x * mu_x + yy - mu_y * mu_y + c2)
    return (num / den).mean()


def ssims(args) -> None:
    x = torch.rand(4, 3, 1150, 1330, device="cuda", requires_grad=True)
    y = torch.rand(4, 3, 1150, 1330, device="cuda")
    reference = ssim(x, y).item()

    def step(fn):
        def run():
            value = fn(x, y)
            value.backward()
            return value
        return run

    timed("ssim", "grouped depthwise conv (today)", step(ssim), args.warmup, args.repeats)
    for name, fn in (("single-channel conv", ssim_single_channel), ("shifted sums eager", ssim_shift),
                     ("shifted sums compiled", torch.compile(ssim_shift)), ("grouped conv compiled", torch.compile(ssim))):
        value = fn(x, y).item() if "compiled" not in name else float("nan")
        timed("ssim", name, step(fn), args.warmup + (2 if "compiled" in name else 0), args.repeats,
              f"|diff| {abs(value - reference):.2e}" if value == value else "")


def cg(args) -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(100_000, 3)) * np.array([0.2, 0.9, 0.15])
    laplacian = knn_laplacian(points, 8)
    b = torch.as_tensor(rng.normal(size=(100_000, 3)), dtype=torch.float32, device="cuda")
    for every in (1, 8, 32):
        system = CGSystem(laplacian, 8.0, tol=1e-5, max_iter=200)
        if "check_every" in CGSystem.__init__.__code__.co_varnames:
            system.check_every = every
        elif every != 1:
            continue
        timed("anchor CG", f"cold solve, check every {every}", lambda: (system.reset(), system.solve(b, "x")), args.warmup, args.repeats,
              f"{system.last_iterations} its")
        noise = [b + 1e-3 * torch.randn_like(b) for _ in range(3)]
        timed("anchor CG", f"warm solve (1e-3 change), check every {every}", lambda: system.solve(noise[np.random.randint(3)], "x"),
              args.warmup, args.repeats, f"{system.last_iterations} its")


def gsplat_calls(args) -> None:
    from gsplat import rasterization
    torch.manual_seed(0)
    k, n, c = 5, 100_000, 4
    means = (torch.randn(k, n, 3, device="cuda") * 0.3).requires_grad_()
    quats = F.normalize(torch.randn(k, n, 4, device="cuda"), dim=-1).requires_grad_()
    scales = torch.full((k, n, 3), 0.01, device="cuda", requires_grad=True)
    opac = torch.full((k, n), 0.5, device="cuda", requires_grad=True)
    sh = (0.1 * torch.randn(k, n, 16, 3, device="cuda")).requires_grad_()
    angles = torch.linspace(0, 2 * np.pi, k * c + 1)[:-1]
    view = torch.zeros(k * c, 4, 4)
    for i, a in enumerate(angles):
        rot = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], dtype=torch.float32)
        view[i, :3, :3] = rot
        view[i, :3, 3] = torch.tensor([0, 0, 3.0])
        view[i, 3, 3] = 1
    view = view.cuda().reshape(k, c, 4, 4)
    K = torch.tensor([[1500.0, 0, 665], [0, 1500, 575], [0, 0, 1]], device="cuda").expand(k, c, 3, 3).contiguous()

    def per_timestep():
        total = 0
        for t in range(k):
            img, _, _ = rasterization(means[t], quats[t], scales[t], opac[t], sh[t], view[t], K[t], 1330, 1150, sh_degree=3,
                                      render_mode="RGB+ED")
            total = total + img.mean()
        total.backward()

    def batched():
        img, _, _ = rasterization(means, quats, scales, opac, sh, view, K, 1330, 1150, sh_degree=3, render_mode="RGB+ED")
        img.mean().backward()

    timed("gsplat", "5 calls of 4 cameras", per_timestep, args.warmup, args.repeats)
    timed("gsplat", "1 batched call (5 x 4)", batched, args.warmup, args.repeats)


def adams(args) -> None:
    decoder = AnchorDecoder(25, 512, 5, 3).cuda()
    params = list(decoder.parameters())
    for p in params:
        p.grad = torch.randn_like(p)
    for name, opt in (("pig Adam (per tensor)", Adam([{"params": params, "lr": 1e-3}])),
                      ("torch Adam foreach", torch.optim.Adam(params, lr=1e-3, foreach=True)),
                      ("torch Adam fused", torch.optim.Adam(params, lr=1e-3, fused=True))):
        timed("adam", name, opt.step, args.warmup, args.repeats)


def lpips_term(args) -> None:
    from pig.metrics.lpips import backbone_features
    net = backbone_features("vgg").cuda().requires_grad_(False)
    x = torch.rand(4, 3, 1150, 1330, device="cuda", requires_grad=True)

    def step(autocast: bool, channels_last: bool):
        def run():
            inp = x.contiguous(memory_format=torch.channels_last) if channels_last else x
            with torch.autocast("cuda", torch.bfloat16, enabled=autocast):
                out = net(inp)
            out.float().mean().backward()
        return run

    timed("lpips vgg", "4 images float32", step(False, False), 1, max(3, args.repeats // 4))
    timed("lpips vgg", "4 images bf16 channels-last", step(True, True), 1, max(3, args.repeats // 4))


def bands(args) -> None:
    """The silhouette band of a batch's 20 masks at 1330 x 1150 (radius 3): one (2r+1)^2 max-pool per side (the
    code before run18) against pig's column-then-row passes."""
    masks = torch.rand(20, 1150, 1330, device="cuda") > 0.5

    def square(mask, radius=3):
        m = mask[:, None].float()
        size = 2 * radius + 1
        dilated = F.max_pool2d(m, size, stride=1, padding=radius) > 0.5
        eroded = -F.max_pool2d(-m, size, stride=1, padding=radius) > 0.5
        return (dilated & ~eroded)[:, 0]

    same = bool(torch.equal(square(masks), boundary_band(masks, 3)))
    timed("band", "square window max-pool", lambda: square(masks), args.warmup, args.repeats)
    timed("band", "column + row max-pool (pig)", lambda: boundary_band(masks, 3), args.warmup, args.repeats,
          "equal" if same else "DIFFERS")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--only", nargs="*", default=["decoders", "ssim", "cg", "gsplat", "adam", "lpips", "band"])
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("fit_kernels_gpu: no CUDA device", file=sys.stderr)
        return 1
    print(f"device {torch.cuda.get_device_name()}, torch {torch.__version__}")
    parts = {"decoders": decoders, "ssim": ssims, "cg": cg, "gsplat": gsplat_calls, "adam": adams, "lpips": lpips_term, "band": bands}
    for name in args.only:
        parts[name](args)
    print("\n| part | alternative | ms fwd+bwd (median) | note |\n|---|---|---|---|")
    for group, name, ms, note in ROWS:
        print(f"| {group} | {name} | {ms:.2f} | {note} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
