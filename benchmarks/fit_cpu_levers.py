"""In-process A/B of the CPU fit's exact levers (cpu-demo): each variant alternated with its baseline, the outputs
compared bit for bit, times as CPU seconds of the one torch thread (time.thread_time: on a shared, loaded machine
a process's CPU time drifts far less than its wall time; the ratio of medians is the figure).

`--lever fill`: short fits with deterministic mode's NaN fill of new tensors (torch.utils.deterministic.
fill_uninitialized_memory) on (before) and off (now); CPU seconds per step over iterations 4..N.
`--lever gathers --against DIR`: projection + compositor of one training view, forward and backward, with DIR's
pig/render/{projection,cpu_compositor}.py (a checkout of the code before) and with this checkout's.

    PYTHONPATH=$PWD python benchmarks/fit_cpu_levers.py --lever fill --capture results/synthetic/subject00/capture
    PYTHONPATH=$PWD python benchmarks/fit_cpu_levers.py --lever gathers --capture results/synthetic/subject00/capture \\
        --avatar results/synthetic/subject00/pig/avatar.pt --against ../main
"""
from __future__ import annotations

import argparse
import importlib.util
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pig.config import derive_preset


def _same(a: Path, b: Path) -> bool:
    x, y = (torch.load(p, weights_only=True)["model"] for p in (a, b))
    return x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)


def lever_fill(capture: Path, steps: int, rounds: int) -> None:
    import pig.avatar.training as training

    workdir = Path(tempfile.mkdtemp(prefix="pig_fit_levers_"))
    derive_preset(workdir / "preset.yaml", "cpu-demo",
                  fit={"iterations": steps, "eval_every": steps, "probe_every": 0, "checkpoint_minutes": 10**6})
    chosen = training.use_deterministic_kernels
    seconds: dict[bool, list[float]] = {True: [], False: []}
    try:
        for r in range(rounds):
            for fill in (True, False) if r % 2 == 0 else (False, True):
                def kernels(device, requested, fill=fill):
                    chosen(device, requested)
                    torch.utils.deterministic.fill_uninitialized_memory = fill

                marks = {}

                def tick(i: int) -> None:
                    if i in (4, steps):
                        marks[i] = time.thread_time()

                training.use_deterministic_kernels = kernels
                try:
                    training.fit(capture, workdir / f"{fill}{r}", str(workdir / "preset.yaml"), threads=1, on_iteration=tick)
                finally:
                    training.use_deterministic_kernels = chosen
                seconds[fill].append((marks[steps] - marks[4]) / (steps - 4))
                print(f"round {r} fill {'on ' if fill else 'off'}: {1000 * seconds[fill][-1]:.0f} ms CPU a step", flush=True)
        same = all(_same(workdir / f"True{r}" / "avatar.pt", workdir / f"False{r}" / "avatar.pt") for r in range(rounds))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    on, off = statistics.median(seconds[True]), statistics.median(seconds[False])
    print(f"\n| fill | ms CPU a step (median of {rounds}) |\n|---|---|\n| on (before) | {1000 * on:.0f} |\n"
          f"| off (now) | {1000 * off:.0f} |\n\noff / on {off / on:.3f}; avatars bit-identical: {same}")


def _module(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def lever_gathers(capture_dir: Path, avatar: Path, against: Path, rounds: int) -> None:
    import pig.render.cpu_compositor as new_compositor
    import pig.render.projection as new_projection
    from pig.avatar.checkpoint import load_avatar
    from pig.avatar.training import use_deterministic_kernels
    from pig.data.capture import Capture

    use_deterministic_kernels(torch.device("cpu"), False)  # the kernels a CPU fit runs

    old_projection = _module(against / "pig/render/projection.py", "projection_before")
    source = (against / "pig/render/cpu_compositor.py").read_text().replace("from .projection", "from pig.render.projection")
    old_path = Path(tempfile.mkdtemp(prefix="pig_fit_levers_")) / "cpu_compositor_before.py"
    old_path.write_text(source)
    old_compositor = _module(old_path, "cpu_compositor_before")
    capture = Capture.load(capture_dir)
    model = load_avatar(avatar, "cpu", capture)
    cameras = [capture.cameras[c] for c in capture.split["train"]["cameras"][:4]]
    viewmats = torch.as_tensor(np.stack([c.viewmat() for c in cameras]), dtype=torch.float32)
    Ks = torch.as_tensor(np.stack([c.K for c in cameras]), dtype=torch.float32)
    width, height = cameras[0].width, cameras[0].height
    with torch.no_grad():
        g = model(torch.tensor([0]), model.num_levels - 1)
    leaves = [t[0].detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
    weights = torch.rand(height, width, 4, generator=torch.Generator().manual_seed(0))

    def run(projection, compositor, c):
        for t in leaves:
            t.grad = None
        t0 = time.thread_time()
        splats = projection.project_splats(*leaves, viewmats[c:c + 1], Ks[c:c + 1], width, height, 1)
        features, alpha = compositor.composite(splats, 1, width, height)
        t1 = time.thread_time()
        ((features[0] * weights).sum() + alpha.sum()).backward()
        t2 = time.thread_time()
        return [features.detach(), alpha.detach(), *(t.grad for t in leaves)], t1 - t0, t2 - t1

    ratios: dict[str, list[float]] = {"forward": [], "backward": []}
    same = True
    for r in range(rounds):
        for c in range(len(cameras)):
            out = {}
            order = [("before", old_projection, old_compositor), ("now", new_projection, new_compositor)]
            for name, projection, compositor in order if (r + c) % 2 == 0 else order[::-1]:
                out[name] = run(projection, compositor, c)
            same &= all(torch.equal(a, b) for a, b in zip(out["before"][0], out["now"][0]))
            ratios["forward"].append(out["now"][1] / out["before"][1])
            ratios["backward"].append(out["now"][2] / out["before"][2])
    shutil.rmtree(old_path.parent, ignore_errors=True)
    print(f"{rounds} rounds x {len(cameras)} training cameras, {len(leaves[0])} splats, 1 thread\n"
          f"now / before, median of the pairs: forward (projection + compositing) {statistics.median(ratios['forward']):.3f}, "
          f"backward {statistics.median(ratios['backward']):.3f}; images and gradients bit-identical: {same}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--lever", choices=["fill", "gathers"], required=True)
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture (the default run's)")
    parser.add_argument("--avatar", type=Path, help="gathers: a fitted avatar.pt of that capture")
    parser.add_argument("--against", type=Path, help="gathers: a checkout of the code before")
    parser.add_argument("--steps", type=int, default=12, help="fill: iterations of each fit (timed from the 4th)")
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.lever == "fill":
        if args.steps <= 4:
            parser.error("--steps must exceed 4")
        lever_fill(args.capture, args.steps, args.rounds)
    else:
        if args.avatar is None or args.against is None:
            parser.error("--lever gathers needs --avatar and --against")
        lever_gathers(args.capture, args.avatar, args.against, args.rounds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
