"""LPIPS's distance head on VGG-shaped taps: the form before (each tap widened to float32, then the unit
normalisation and the difference as separate full-size tensors) against pig.metrics.lpips's (the norm read off the
tap in float32, the difference in one `addcdiv`), in the same process, rounds interleaved.

Taps: relu1_2 .. relu5_3 of a (B, 3, H, W) image (64, 128, 256, 512, 512 channels at 1, 1/2, 1/4, 1/8, 1/16 of the
side), random, in `--dtype` (float16 is the evaluate preset's lowered arithmetic; CPUs have no float16 arithmetic,
so time it on CUDA). Rows: the render side against cached reference taps (per LOD) and the reference side (once a
view), in ms per image, and the largest |new - old| over the images.

    python benchmarks/lpips_distance.py                      # CPU, float32 taps, 1330 x 1150
    python benchmarks/lpips_distance.py --device cuda --dtype float16 --batch 16
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from pig.metrics.lpips import _channel_norm, _unit

CHANNELS, STRIDES = (64, 128, 256, 512, 512), (1, 2, 4, 8, 16)


def old_unit(tap: torch.Tensor) -> torch.Tensor:
    wide = tap.float()
    return wide / (wide.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)


def old_distance(taps, references, weights) -> torch.Tensor:
    return sum(torch.nn.functional.conv2d((old_unit(fx) - ny).pow(2), w).mean(dim=(1, 2, 3))
               for fx, ny, w in zip(taps, references, weights))


def new_distance(taps, references, weights) -> torch.Tensor:
    return sum(torch.nn.functional.conv2d(torch.addcdiv(ny, fx, _channel_norm(fx), value=-1).square(), w)
               .mean(dim=(1, 2, 3)) for fx, ny, w in zip(taps, references, weights))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1330)
    parser.add_argument("--height", type=int, default=1150)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--dtype", choices=["float32", "float16", "bfloat16"], default="float32")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    generator = torch.Generator(device).manual_seed(0)

    def taps():
        return [torch.rand((args.batch, c, -(-args.height // s), -(-args.width // s)), generator=generator,
                           device=device).mul_(4).to(dtype) for c, s in zip(CHANNELS, STRIDES)]

    render, truth = taps(), taps()
    weights = [torch.rand((1, c, 1, 1), generator=generator, device=device) for c in CHANNELS]
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    forms = {
        "render vs reference taps, old": lambda refs: old_distance(render, refs["old"], weights),
        "render vs reference taps, new": lambda refs: new_distance(render, refs["new"], weights),
        "reference taps, old": lambda refs: [old_unit(t) for t in truth],
        "reference taps, new": lambda refs: [_unit(t) for t in truth],
    }
    with torch.no_grad():
        references = {"old": [old_unit(t) for t in truth], "new": [_unit(t) for t in truth]}
        times: dict[str, list[float]] = {name: [] for name in forms}
        for _ in range(args.rounds + 1):  # the first round warms up
            for name, form in forms.items():
                sync()
                start = time.perf_counter()
                form(references)
                sync()
                times[name].append(time.perf_counter() - start)
        gap = (new_distance(render, references["new"], weights)
               - old_distance(render, references["old"], weights)).abs().max().item()
    print(f"LPIPS distance head, {args.batch} x {args.width} x {args.height} VGG taps in {args.dtype}, device "
          f"{device}, median of {args.rounds} rounds (threads {torch.get_num_threads()})")
    print(f"{'part':<34} {'ms/image':>9} {'new / old':>10}")
    for name, values in times.items():
        ms = 1000 * statistics.median(values[1:]) / args.batch
        base = name.replace(", new", ", old")
        ratio = statistics.median(values[1:]) / statistics.median(times[base][1:]) if base != name else None
        print(f"{name:<34} {ms:>9.2f} {'' if ratio is None else f'{ratio:>10.3f}'}")
    print(f"largest |LPIPS new - old| over the images: {gap:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
