"""The training step's compiled L1 + SSIM loss (pig.avatar.training.LossTerms: image_loss with the shifted-sum
blur under torch.compile) with SSIM's Gaussian window made four ways, forward and backward at the `paper` batch:

- `constants`: the window as Python numbers, constants of the kernels (8393f7b to 6958fcf);
- `device`: made inside the compiled graph on the device (2e5d54c and the commits since 5cc8b8f);
- `host`: made inside the compiled graph on the host, then copied to the device (26bda42 and before);
- `input`: made once on the device before compilation, a tensor the compiled graph reads (this code: LossTerms makes
  it and passes it as image_loss's `ssim_window`).

run33-run34 found a fit's peak memory 13-17 GiB higher and its backward 12 ms longer at 2e5d54c than at 26bda42 on
one machine (benchmarks/NOTES.md, "the peak memory of a fit step"); the window is the one change between them inside
a compiled region of the step (run35 confirmed it: `device` 22.3 GiB above the inputs against 4.8-5.5). Each form runs
in its own process (its own compilation), and prints the peak memory above the inputs and the median ms of forward +
backward; `--rounds` runs the forms round-robin that many times, so that a form's time is told from its place in the
order (run35's one round had `host` 5 ms faster than `constants`, which ran first):

    python benchmarks/loss_window_gpu.py [--views 20] [--height 1150] [--width 1330] [--iterations 20] [--rounds 2]
        [--code-dir DIR]

`--code-dir`: each form's compiled kernels as inductor wrote them (TORCH_LOGS=output_code) in DIR/FORM.txt, to read
where a form's memory goes.

On a CPU (no peak memory) it checks only that the forms give the same loss and gradient.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import torch

import pig.metrics.ssim as ssim_module
from pig.avatar.losses import image_loss

FORMS = ("constants", "device", "host", "input")


def window_made_on(where: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The window as the earlier code made it: the taps' arithmetic on `where` ("device" or "host"), then moved."""
    offsets = torch.arange(-ssim_module.RADIUS, ssim_module.RADIUS + 1, dtype=torch.float64,
                           device=device if where == "device" else "cpu")
    taps = torch.exp(-0.5 * (offsets / ssim_module.SIGMA) ** 2)
    return (taps / taps.sum()).to(dtype=dtype, device=device)


def use_form(form: str, device: str) -> torch.Tensor | None:
    """The window to pass to the compiled loss for `form` ("input"), or None after pointing SSIM's "shift" blur at
    the window of `form` (inside the compiled loss, as the code of that form did)."""
    if form == "input":
        return ssim_module.gaussian_window(torch.float32, device)
    if form == "constants":
        taps = tuple(window_made_on("host", torch.float64, torch.device("cpu")).tolist())
        ssim_module.BLURS["shift"] = lambda images, _: ssim_module._blur_shifted(images, taps)
        return None
    ssim_module.BLURS["shift"] = lambda images, _: ssim_module._blur_shifted(
        images, window_made_on(form, images.dtype, images.device))
    return None


def inputs(views: int, height: int, width: int, device: str, seed: int = 0):
    g = torch.Generator(device=device).manual_seed(seed)
    render = torch.rand(views, height, width, 3, generator=g, device=device, requires_grad=True)
    target = torch.rand(views, height, width, 3, generator=g, device=device)
    band = torch.rand(views, height, width, generator=g, device=device) < 0.05
    return render, target, band, torch.zeros(3, device=device)


def run_form(form: str, views: int, height: int, width: int, iterations: int, device: str) -> dict:
    """One form in this process: the loss and gradient norm, and on CUDA the peak memory above the inputs (GiB) and
    the median ms of forward + backward after two compiling calls."""
    window = use_form(form, device)
    loss_fn = torch.compile(
        lambda r, t, b, bg: image_loss(r, t, b, bg, (0.8, 0.2, 0.0), None, "shift", window)["total"])
    render, target, band, background = inputs(views, height, width, device)
    cuda = device.startswith("cuda")
    times = []
    for i in range(iterations + 2):
        render.grad = None
        if cuda and i == 2:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
        start = time.perf_counter()
        loss = loss_fn(render, target, band, background)
        loss.backward()
        if cuda:
            torch.cuda.synchronize()
        times.append(1000 * (time.perf_counter() - start))
    record = {"form": form, "loss": loss.item(), "grad_norm": render.grad.norm().item(),
              "ms": statistics.median(times[2:]) if iterations else None}
    if cuda:
        record["peak_gib"] = (torch.cuda.max_memory_allocated() - base) / 2**30
    return record


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=20)
    parser.add_argument("--height", type=int, default=1150)
    parser.add_argument("--width", type=int, default=1330)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=2, help="the forms round-robin this many times")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--code-dir", help="write each form's generated code (TORCH_LOGS=output_code) to DIR/FORM.txt")
    parser.add_argument("--form", choices=FORMS, help=argparse.SUPPRESS)  # one form, in this process
    args = parser.parse_args(argv)
    if args.form:
        print(json.dumps(run_form(args.form, args.views, args.height, args.width, args.iterations, args.device)))
        return 0
    records = {form: [] for form in FORMS}
    for round_index in range(args.rounds):
        for form in FORMS:
            command = [sys.executable, __file__, "--form", form, "--views", str(args.views), "--height",
                       str(args.height), "--width", str(args.width), "--iterations", str(args.iterations),
                       "--device", args.device]
            write_code = args.code_dir and round_index == 0
            env = dict(os.environ, **({"TORCH_LOGS": "output_code"} if write_code else {}))
            done = subprocess.run(command, capture_output=True, text=True, check=True, env=env)
            if write_code:
                os.makedirs(args.code_dir, exist_ok=True)
                with open(os.path.join(args.code_dir, f"{form}.txt"), "w") as file:
                    file.write(done.stderr)
            records[form].append(json.loads(done.stdout.strip().splitlines()[-1]))
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    print(f"device: {name}; compiled L1 + SSIM (shift blur), {args.views} x {args.height} x {args.width}, "
          f"forward + backward, median of {args.iterations}, forms round-robin {args.rounds} times")
    print("| window | peak GiB above inputs | ms (median of rounds) | ms by round | loss | gradient norm |")
    print("|---|---|---|---|---|---|")
    for form, runs in records.items():
        peaks = [r["peak_gib"] for r in runs if "peak_gib" in r]
        times = [r["ms"] for r in runs if r["ms"] is not None]
        peak = f"{max(peaks):.2f}" if peaks else "-"
        ms = f"{statistics.median(times):.1f}" if times else "-"
        by_round = " / ".join(f"{t:.1f}" for t in times) or "-"
        print(f"| {form} | {peak} | {ms} | {by_round} | {runs[0]['loss']:.7f} | {runs[0]['grad_norm']:.7g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
