"""Where a CPU fit step goes (cpu-demo preset): a per-phase table of the default fit's training iterations.

The fit's own phases (`fit(phase=...)`: sample, model, render, loss, backward, step) split into the parts the
issue names: the model's forward by submodule (grid with its preconditioned solve, anchor solve, body model,
decoders, refiner; the rest of the forward is the transport and splat assembly), the render into projection and
compositor, and the backward by autograd node from torch.profiler (the compositor's closed form, the decoders'
matmuls, the solves' backward, the rest). Times are CPU wall seconds of iterations `--skip`..`--steps`; on a
loaded machine the shares stay meaningful (every phase slows alike), the absolute times do not.

    PYTHONPATH=$PWD python benchmarks/fit_cpu_profile.py --capture results/synthetic/subject00/capture \\
        --steps 60 --threads 2
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
import yaml

from fit_gpu import PhaseTimer
from pig.config import load_preset

# Backward autograd nodes by substring of their name -> part (first match wins); the rest is "backward.other".
BACKWARD_PARTS = [("_BandComposite", "backward.compositor"), ("Solve", "backward.solves"),
                  ("GridSampler", "backward.grid_lookup"), ("Addmm", "backward.matmuls"), ("Mm", "backward.matmuls"),
                  ("Convolution", "backward.loss_blur"), ("Index", "backward.gathers"), ("Gather", "backward.gathers")]


@contextmanager
def _timed_render(phases: PhaseTimer):
    """The render phase split into projection and compositor by wrapping the two functions api.py calls."""
    import pig.render.api as api

    project, composite = api.project_splats, api.composite

    def wrap(fn, name):
        def timed(*args, **kwargs):
            with phases(name):
                return fn(*args, **kwargs)
        return timed

    api.project_splats, api.composite = wrap(project, "render.projection"), wrap(composite, "render.compositor")
    try:
        yield
    finally:
        api.project_splats, api.composite = project, composite


def backward_nodes(profile) -> dict[str, float]:
    """Seconds of the profiled backward per autograd node (CPU time of the node with the ops under it)."""
    prefix = "autograd::engine::evaluate_function: "
    return {e.key[len(prefix):]: e.cpu_time_total / 1e6 for e in profile.key_averages() if e.key.startswith(prefix)}


def backward_parts(nodes: dict[str, float]) -> dict[str, float]:
    """The nodes' seconds summed by part (BACKWARD_PARTS)."""
    parts: dict[str, float] = defaultdict(float)
    for node, seconds in nodes.items():
        parts[next((p for key, p in BACKWARD_PARTS if key in node), "backward.other")] += seconds
    return parts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture (the default run's)")
    parser.add_argument("--preset", default="cpu-demo")
    parser.add_argument("--set", action="append", default=[], help="section.key=value override (repeatable)")
    parser.add_argument("--steps", type=int, default=60, help="iterations in all")
    parser.add_argument("--skip", type=int, default=10, help="first iterations left out of the table")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--nodes", type=int, default=15, help="autograd nodes listed by their share of the backward")
    args = parser.parse_args(argv)
    if args.steps <= args.skip:
        parser.error("--steps must exceed --skip")
    from pig.avatar.training import fit

    preset = load_preset(args.preset)
    preset.pop("_path")
    for item in args.set:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        preset.setdefault(section, {})[name] = yaml.safe_load(value)
    # One iteration past the table: the fit's closing evaluation runs after the last timed one.
    preset["fit"].update(iterations=args.steps + 1, eval_every=10**6, probe_every=0, checkpoint_minutes=10**6)
    workdir = Path(tempfile.mkdtemp(prefix="pig_fit_cpu_profile_"))
    (workdir / "preset.yaml").write_text(yaml.safe_dump(preset))

    phases = PhaseTimer(synchronize=lambda: None)  # the CPU: nothing to wait for
    profile = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
    marks = {}

    def tick(i: int) -> None:
        phases.end_iteration()
        phases.active = args.skip <= i < args.steps
        if i == args.skip:
            marks["start"] = time.perf_counter()
        if i == args.steps:
            marks["stop"] = time.perf_counter()

    try:
        with _timed_render(phases):
            fit(args.capture, workdir / "fit", str(workdir / "preset.yaml"), threads=args.threads, on_iteration=tick,
                phase=phases)
        # The backward's split needs the profiler, which slows the ops it records: a second run, shares only.

        def tick_profile(i: int) -> None:
            if i == args.skip:
                profile.start()
            if i == args.steps:
                profile.stop()

        shutil.rmtree(workdir / "fit")
        fit(args.capture, workdir / "fit", str(workdir / "preset.yaml"), threads=args.threads, on_iteration=tick_profile)
    finally:
        phases.close()
        shutil.rmtree(workdir, ignore_errors=True)

    timed = args.steps - args.skip
    total = marks["stop"] - marks["start"]
    per = {name: seconds / timed for name, seconds in phases.totals_s().items()}
    model_parts = sum(v for k, v in per.items() if k.startswith("model."))
    per["model.transport_and_splats"] = per.get("model", 0.0) - model_parts
    render_parts = per.get("render.projection", 0.0) + per.get("render.compositor", 0.0)
    per["render.other"] = per.get("render", 0.0) - render_parts
    nodes = backward_nodes(profile)
    back = backward_parts(nodes)
    back_total = sum(back.values())
    for part, seconds in back.items():  # the measured backward split in the profiled run's proportions
        per[part] = per.get("backward", 0.0) * seconds / back_total if back_total else 0.0
    per["other (logging, lr schedule, hooks)"] = total / timed - sum(
        per.get(k, 0.0) for k in ("sample", "model", "render", "loss", "backward", "step"))
    load = os.getloadavg()
    print(f"{timed} iterations ({args.skip}..{args.steps}), {args.threads} threads, {1000 * total / timed:.1f} ms/it, "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print("\n| phase | ms/it | share of a step |\n|---|---|---|")
    order = ["sample", "model", "model.grid", "model.anchor_solve", "model.body", "model.decoders", "model.refiner",
             "model.transport_and_splats", "render", "render.projection", "render.compositor", "render.other", "loss",
             "backward", *sorted(k for k in per if k.startswith("backward.")), "step",
             "other (logging, lr schedule, hooks)"]
    for name in order:
        if name in per:
            indent = "  " if "." in name and not name.startswith("other") else ""
            print(f"| {indent}{name} | {1000 * per[name]:.1f} | {100 * per[name] * timed / total:.1f} % |")
    print("\n| autograd node (profiled run) | share of the backward |\n|---|---|")
    for node, seconds in sorted(nodes.items(), key=lambda item: -item[1])[:args.nodes]:
        print(f"| {node} | {100 * seconds / back_total:.1f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
