"""The host's share of one `paper` step, measured on the CPU: per phase, ms, aten ops and GPU host syncs.

The GPU scaling table (benchmarks/NOTES.md, "the scaling table on 1, 2 and 4 H200s") stops shrinking at 5 views a
rank; the question is whether the step is then bound by the host (Python, autograd, dispatch, launches). This runs
the fit's own loop (pig.avatar.training.fit, and pig.avatar.parallel_fit.fit_parallel's ranks on gloo) with the
`paper` preset's switches that shape the host's work, at sizes where the kernels cost next to nothing:

- kept: the LPIPS term in the `mmlphuman` form on random VGG weights, on from the first iteration with its random
  windows (as in the GPU table's profiled iterations), the anchors' CG solve (`precond.knn_solver: cg`), the grid's
  six levels of 16 features (sides 4..14 instead of 8..88), 4 LODs, SH degree 3, 5 + 3 decoder and refiner
  layers, 5 timesteps x 4 views, batched render, host band, fused Adam, `log_every` 50, `fit.shard_solves` in the
  data-parallel runs;
- shrunk: images (`--size` px, default 32), anchors 1200, decoder width 32, LPIPS crop 16 (VGG's least);
- off: compilation (`fit.compile`, `compile_posing`, `lpips_compile`, `precond.cg_compile`: the GPU compiles them,
  so their eager op counts here are upper bounds of the GPU's launches) and bf16 autocast (float32).

One torch thread: each phase's main-thread CPU time (time.thread_time) is then its host work plus the tiny
kernels, and stays meaningful on a loaded machine (waits for other processes do not count; a rank's wall time
includes its waits for the other ranks, and N ranks on fewer cores share them). Per view count of the
step (`--views`: 20, 10, 5 as 5 timesteps x 4, 2, 1 cameras), one fit of `--warmup` + 3 windows of `--steps`
iterations: (1) per phase the median wall and CPU ms; (2) per phase the aten ops dispatched (a TorchDispatchMode
counter: all, those that are not views, i.e. launch a kernel or allocate on a GPU, and those that make a GPU's host
wait for the device: _local_scalar_dense (.item(), float(), bool() of a tensor), nonzero, masked_select, unique and
kin); (3) cProfile's top functions by cumulative and by own time. `--ranks N` adds rank 0 of an N-process gloo
fit (the data-parallel path: gradient hooks, all-reduces, broadcasts, the LPIPS draws, digest checks) at 20 views
an iteration, i.e. 20/N a rank.

    PYTHONPATH=$PWD python benchmarks/host_overhead_cpu.py --views 20 10 5 --ranks 2 4
"""
from __future__ import annotations

import argparse
import cProfile
import functools
import json
import pstats
import statistics
import sys
import tempfile
import time
from collections import Counter, defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

sys.path.insert(0, str(Path(__file__).parent))
from fit_gpu import MODULES  # noqa: E402

from pig.config import derive_preset  # noqa: E402

# Ops that make the host wait for a GPU's queue: their result's size or value is read on the host. A blocking copy of
# host data to the device waits too, but is no op on the CPU (tests/test_fit_parallel.py's _BlockingCopies checks
# the model's forward for them).
SYNCING = {"_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique", "_unique2", "unique_dim",
           "unique_consecutive", "repeat_interleave", "equal", "is_nonzero"}
PHASES = ("sample", "model", "render", "loss", "backward", "reduce", "solve_forward", "solve_backward", "step")
WINDOWS = ("time", "count", "profile")
# Sub-phases by module (the outermost when they nest): fit_gpu's, and the LPIPS network inside `loss`.
SUBMODULES = {**MODULES, "TrainingLPIPS": "loss.lpips_net"}


class OpCounter(TorchDispatchMode):
    """Counts the aten ops dispatched, by the phase `where()` names when each is dispatched."""

    def __init__(self, where):
        super().__init__()
        self.where = where
        self.ops: Counter = Counter()  # phase -> all ops
        self.compute: Counter = Counter()  # phase -> ops that are not views
        self.syncs: Counter = Counter()  # phase -> ops that wait for the device on a GPU
        self.sync_names: Counter = Counter()  # (phase, op) -> count

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        phase = self.where()
        if phase == "backward":  # by the phase whose forward made the node that runs it (PhaseTagger), else its name
            node = torch._C._current_autograd_node()
            made = node.metadata.get("phase") if node is not None else None
            if made is not None and not node.metadata.get("spread"):
                # The nodes a tagged node feeds run after it: untagged ones (made inside a Python-level torch function,
                # which the tagger sees whole) take its phase.
                for child, _ in node.next_functions:
                    if child is not None and "phase" not in child.metadata:
                        child.metadata["phase"] = made
                node.metadata["spread"] = True
            phase = f"backward:{made or (type(node).__name__ if node is not None else 'engine')}"
        self.ops[phase] += 1
        if not func.is_view:
            self.compute[phase] += 1
        name = func._schema.name.split("::")[-1]
        if name in SYNCING:
            self.syncs[phase] += 1
            self.sync_names[(phase, name)] += 1
        return func(*args, **(kwargs or {}))


class PhaseTagger(TorchFunctionMode):
    """Tags each autograd node made by a torch function with the phase `where()` names then, so that the backward's
    ops can be counted by the forward phase they differentiate (nodes of autograd.Function.apply go untagged)."""

    def __init__(self, where):
        super().__init__()
        self.where = where

    def __torch_function__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_leaves(out):
            if isinstance(t, torch.Tensor) and t.grad_fn is not None and "phase" not in t.grad_fn.metadata:
                t.grad_fn.metadata["phase"] = self.where()
        return out


class HostMeter:
    """The fit's `phase` hook and `on_iteration` callback: iterations warmup.. are timed, then counted, then profiled
    (`steps` each); the avatar's submodules (fit_gpu.MODULES) are phases inside `model`, the LPIPS network and the
    L1 + SSIM loss inside `loss` (regions the GPU compiles). Ops outside any phase count as "other", the backward's
    by the forward phase that made their autograd node. At the end of the last window the record is written to `out`
    (JSON) when given; `close` removes the hooks."""

    def __init__(self, warmup: int, steps: int, out: str | None = None):
        self.warmup, self.steps, self.out = warmup, steps, out
        self.stack: list[str] = []
        self.wall: list[dict] = []  # per timed iteration: phase -> seconds (inclusive)
        self.cpu: list[dict] = []
        self.iteration_wall: list[float] = []
        self.iteration_cpu: list[float] = []
        where = lambda: self.stack[-1] if self.stack else "other"
        self.counter, self.tagger = OpCounter(where), PhaseTagger(where)
        self.profiler = cProfile.Profile()
        self.window = None
        self._mark = None
        self._hooks = [torch.nn.modules.module.register_module_forward_pre_hook(self._pre),
                       torch.nn.modules.module.register_module_forward_hook(self._post)]
        import pig.avatar.training as training

        image_loss = training.image_loss  # LossTerms calls the module's name at each evaluation

        def timed_image_loss(*args, **kwargs):
            with self("loss.l1_ssim"):
                return image_loss(*args, **kwargs)

        training.image_loss = timed_image_loss
        self._restore = lambda: setattr(training, "image_loss", image_loss)

    def close(self) -> None:
        for hook in self._hooks:
            hook.remove()
        self._restore()

    def window_of(self, iteration: int) -> str | None:
        """The window iteration `iteration` (0-based) lies in."""
        k = (iteration - self.warmup) // self.steps
        return WINDOWS[k] if 0 <= k < len(WINDOWS) and iteration >= self.warmup else None

    @contextmanager
    def __call__(self, name: str):
        self.stack.append(name)
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            self.stack.pop()
            if self.window == "time":
                self.wall[-1][name] += time.perf_counter() - t0
                self.cpu[-1][name] += time.thread_time() - c0

    def _pre(self, module, args):
        name = SUBMODULES.get(type(module).__name__)
        if name is not None and self.window is not None and not any("." in s for s in self.stack):
            self.stack.append(name)
            module._host_meter_start = (time.perf_counter(), time.thread_time())

    def _post(self, module, args, output):
        start = getattr(module, "_host_meter_start", None)
        if start is not None and self.stack and self.stack[-1] == SUBMODULES[type(module).__name__]:
            self.stack.pop()
            del module._host_meter_start
            if self.window == "time":
                self.wall[-1][self.stack_name(module)] += time.perf_counter() - start[0]
                self.cpu[-1][self.stack_name(module)] += time.thread_time() - start[1]

    @staticmethod
    def stack_name(module) -> str:
        return SUBMODULES[type(module).__name__]

    def begin(self, iteration: int) -> None:
        """Before iteration `iteration` (0-based): enter its window's instrument."""
        self.window = self.window_of(iteration)
        if self.window == "time":
            self.wall.append(defaultdict(float))
            self.cpu.append(defaultdict(float))
            self._mark = (time.perf_counter(), time.thread_time())
        elif self.window == "count":
            self.tagger.__enter__()
            self.counter.__enter__()
        elif self.window == "profile":
            self.profiler.enable()

    def end(self) -> None:
        if self.window == "time":
            self.iteration_wall.append(time.perf_counter() - self._mark[0])
            self.iteration_cpu.append(time.thread_time() - self._mark[1])
        elif self.window == "count":
            self.counter.__exit__(None, None, None)
            self.tagger.__exit__(None, None, None)
        elif self.window == "profile":
            self.profiler.disable()

    def on_iteration(self, iteration: int) -> None:
        """After iteration `iteration` (1-based; the fit calls it last in an iteration): close that iteration's
        window, open the next one's."""
        self.end()
        if iteration == self.warmup + len(WINDOWS) * self.steps:
            self.window = None
            if self.out is not None:
                Path(self.out).write_text(json.dumps(self.record()))
            return
        self.begin(iteration)

    def record(self) -> dict:
        phases = sorted({name for it in self.wall for name in it} | set(self.counter.ops))
        per_step = lambda counter: {name: counter[name] / self.steps for name in counter}
        return {
            "wall_ms": {p: 1000 * statistics.median(it.get(p, 0.0) for it in self.wall) for p in phases},
            "cpu_ms": {p: 1000 * statistics.median(it.get(p, 0.0) for it in self.cpu) for p in phases},
            "step_wall_ms": 1000 * statistics.median(self.iteration_wall),
            "step_cpu_ms": 1000 * statistics.median(self.iteration_cpu),
            "ops": per_step(self.counter.ops), "compute": per_step(self.counter.compute),
            "syncs": per_step(self.counter.syncs),
            "sync_names": {f"{p}:{n}": c / self.steps for (p, n), c in self.counter.sync_names.items()},
            "cumulative": top_functions(self.profiler, "cumulative", self.steps),
            "own": top_functions(self.profiler, "tottime", self.steps),
        }


def top_functions(profiler: cProfile.Profile, key: str, steps: int, count: int = 15) -> list[tuple]:
    """(calls, own ms, cumulative ms per step, function) of the `count` first functions by `key`."""
    stats = pstats.Stats(profiler)
    index = {"cumulative": 3, "tottime": 2}[key]
    rows = sorted(stats.stats.items(), key=lambda item: -item[1][index])[:count]
    out = []
    for (path, line, name), (_, calls, own, cumulative, _) in rows:
        short = path
        for marker in ("/pig/", "/torch/", "/benchmarks/"):
            if marker in path:
                short = marker.strip("/") + "/" + path.split(marker, 1)[1]
                break
        out.append((calls / steps, 1000 * own / steps, 1000 * cumulative / steps, f"{short}:{line}({name})"))
    return out


def eager_op_us(repeats: int = 20000) -> tuple[float, float]:
    """Main-thread CPU microseconds per op of this process: an add of two 1-element tensors, without and with
    autograd recording (the least an eager op costs the host here, before any GPU launch)."""
    a, b = torch.ones(1), torch.ones(1, requires_grad=True)
    out = []
    for x in (torch.ones(1), b):
        t0 = time.thread_time()
        for _ in range(repeats):
            a + x
        out.append(1e6 * (time.thread_time() - t0) / repeats)
    return out[0], out[1]


def write_preset(folder: Path, timesteps: int, views: int, iterations: int, shard_solves: bool) -> str:
    """The `paper` preset with the host-shaping switches kept and the sizes shrunk (module docstring)."""
    return str(derive_preset(
        folder / f"preset_{timesteps}x{views}.yaml", "paper",
        avatar=dict(num_anchors=1200, hidden_width=32),
        field=dict(resolutions=[4, 6, 8, 10, 12, 14]),
        fit=dict(iterations=iterations, views=views, timesteps=timesteps, lpips_weights="random", lpips_crop=16,
                 lpips_start=0.0, lpips_patches_from=0.0, eval_every=10**9, eval_frames=1, checkpoint_minutes=10**6,
                 compile=False, compile_posing=False, lpips_compile=False, precision="float32", cpu_threads=1,
                 view_cache=256, loader_workers=1, prefetch=2, shard_solves=shard_solves),
        precond=dict(cg_compile=False)))


def make_capture(root: Path, size: int) -> Path:
    """A synthetic capture with 5+ training frames each seen by 4+ training cameras, `size` px a side (the tests'
    recipe, benchmarks/precond_adam_power.small_capture, with more cameras and frames)."""
    from pig.data.synthetic import SyntheticConfig, generate_capture
    from pig.stages.preprocess import main as preprocess

    raw = generate_capture(root / "raw", SyntheticConfig(cameras=8, frames=8, width=size, height=size, workers=1),
                           progress=False)
    preprocess(["--input", str(raw), "--output", str(root / "capture"), "--preset", "test", "--format", "thuman4",
                "--body-model", str(raw / "body_model.npz"), "--no-progress"])
    return root / "capture"


def one_process(capture: Path, work: Path, timesteps: int, views: int, warmup: int, steps: int) -> dict:
    from pig.avatar.training import fit

    meter = HostMeter(warmup, steps)
    # One iteration past the windows: the fit's last one ends with its held-out evaluation.
    preset = write_preset(work, timesteps, views, warmup + len(WINDOWS) * steps + 1, False)
    try:
        fit(capture, work / f"fit_{timesteps}x{views}", preset, on_iteration=meter.on_iteration, phase=meter,
            progress_s=1e9, overwrite=True)
    finally:
        meter.close()
    return meter.record()


def _rank_hooks(folder: str, warmup: int, steps: int, rank: int):
    from pig.avatar.parallel_fit import RankHooks

    meter = HostMeter(warmup, steps, str(Path(folder) / f"rank{rank}.json"))
    return RankHooks(on_iteration=meter.on_iteration, phase=meter)


def data_parallel(capture: Path, work: Path, ranks: int, warmup: int, steps: int) -> dict:
    from pig.avatar.parallel_fit import fit_parallel

    folder = work / f"ranks{ranks}"
    folder.mkdir()
    preset = write_preset(folder, 5, 4, warmup + len(WINDOWS) * steps + 1, True)
    fit_parallel(capture, folder / "fit", preset, "pig", ranks, "cpu", progress_s=1e9,
                 rank_hooks=functools.partial(_rank_hooks, str(folder), warmup, steps), timeout_s=600)
    return json.loads((folder / "rank0.json").read_text())


def print_tables(runs: dict[str, dict], steps: int) -> None:
    names = list(runs)
    print(f"\nPer phase, median of {steps} steps (ms; one torch thread; model.* lie inside model; other: outside any phase)")
    print("\n| phase | " + " | ".join(f"{n} wall | {n} CPU" for n in names) + " |")
    print("|---|" + "---|---|" * len(names))
    phases = [p for p in (*PHASES, *sorted(set(MODULES.values())), "solve_forward.own", "solve_backward.own")
              if any(p in r["cpu_ms"] for r in runs.values())]
    for p in phases:
        print(f"| {p} | " + " | ".join(f"{r['wall_ms'].get(p, 0):.1f} | {r['cpu_ms'].get(p, 0):.1f}" for r in runs.values()) + " |")
    print("| iteration (on_iteration to on_iteration) | "
          + " | ".join(f"{r['step_wall_ms']:.1f} | {r['step_cpu_ms']:.1f}" for r in runs.values()) + " |")

    print("\nAten ops dispatched per step, by phase (all / not views / GPU host syncs; phases exclusive: model's and "
          "loss's exclude their sub-phases; the backward's by autograd node below)")
    print("\n| phase | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    forward = sorted({p for r in runs.values() for p in r["ops"] if not p.startswith("backward:")},
                     key=lambda p: (p.split(".")[0] not in PHASES, PHASES.index(p.split(".")[0]) if p.split(".")[0] in PHASES
                                    else 0, p))
    cell = lambda r, keys: (f"{sum(r['ops'].get(k, 0) for k in keys):.0f} / {sum(r['compute'].get(k, 0) for k in keys):.0f}"
                            f" / {sum(r['syncs'].get(k, 0) for k in keys):.0f}")
    for p in forward:
        print(f"| {p} | " + " | ".join(cell(r, [p]) for r in runs.values()) + " |")
    print("| backward (all nodes) | " + " | ".join(cell(r, [k for k in r["ops"] if k.startswith("backward:")])
                                                 for r in runs.values()) + " |")
    print("| total | " + " | ".join(cell(r, list(r["ops"])) for r in runs.values()) + " |")
    first = next(iter(runs.values()))
    nodes = sorted((k for k in first["ops"] if k.startswith("backward:")), key=lambda k: -first["ops"][k])[:15]
    print(f"\nThe backward's aten ops per step by the forward phase that made their autograd node (else the node's "
          f"name; the {len(nodes)} with the most in the first run)")
    print("\n| forward phase or node | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for k in nodes:
        print(f"| {k.split(':', 1)[1]} | " + " | ".join(cell(r, [k]) for r in runs.values()) + " |")
    for name, r in runs.items():
        syncs = ", ".join(f"{k} {v:g}" for k, v in sorted(r["sync_names"].items(), key=lambda kv: -kv[1]))
        print(f"\nGPU host syncs per step, {name}: {syncs or 'none'}")
    for name, r in runs.items():
        for key, title in (("cumulative", "cumulative"), ("own", "own (self)")):
            print(f"\ncProfile, {name}: top {len(r[key])} by {title} time (per step: calls, own ms, cumulative ms; "
                  "the profiler's own cost inflates both)")
            for calls, own, cumulative, where in r[key]:
                print(f"  {calls:8.0f} {own:8.2f} {cumulative:8.2f}  {where}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, nargs="+", default=[20, 10, 5], choices=[20, 10, 5],
                        help="views of the one-process step: 5 timesteps x 4, 2 or 1 cameras")
    parser.add_argument("--ranks", type=int, nargs="*", default=[2], help="rank 0 of a gloo fit with this many processes")
    parser.add_argument("--size", type=int, default=32, help="image side, px")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--steps", type=int, default=5, help="iterations per window (timed, counted, profiled)")
    parser.add_argument("--workdir", type=Path, help="kept (default: a temporary folder)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        capture = make_capture(work / "data", args.size)
        runs = {}
        for views in args.views:
            runs[f"1 proc, {views} views"] = one_process(capture, work, 5, views // 5, args.warmup, args.steps)
        for ranks in args.ranks:
            runs[f"rank 0 of {ranks}, {20 / ranks:g} views"] = data_parallel(capture, work, ranks, args.warmup, args.steps)
        print(f"\n`paper` step's host work on the CPU ({torch.__version__}, {args.size} px images, compilation off, "
              f"float32, one torch thread; {args.warmup} warm-up iterations, then {args.steps} timed, {args.steps} "
              f"counted, {args.steps} profiled)")
        plain, recorded = eager_op_us()
        print(f"Eager op floor on this CPU (1-element add, main-thread CPU time): {plain:.1f} us, {recorded:.1f} us "
              "with autograd recording")
        print_tables(runs, args.steps)


if __name__ == "__main__":
    main()
