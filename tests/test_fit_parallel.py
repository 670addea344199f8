"""Data-parallel fit (pig.avatar.distributed) on the CPU with gloo: the split of an iteration's views, 2 processes
against 1 on one step (gradients, loss, weights), rank 0's clock deciding for all, resume across process counts."""
import ast
import csv
import functools
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections import Counter
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, replace
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
from torch.multiprocessing import start_processes
from torch.overrides import TorchFunctionMode

from pig.avatar.batches import Picks, Sampler, TrainingBatches, ViewSource
from pig.avatar.build import body_model_npz, build_avatar, build_optimizers
from pig.avatar.config import AvatarConfig
from pig.avatar.distributed import (GradientReducer, Parallel, ShardedSampler, SolveShards, shard_loss, shard_picks,
                                    solve_costs, solve_owners, split_pairs)
from pig.avatar.parallel_fit import (RankHooks, core_of, fit_parallel, gpu_local_cpus, parse_cpu_list, rank_cpu_sets,
                                     rank_threads)
from pig.avatar.fit_config import FitConfig
from pig.avatar.losses import lpips_term
from pig.avatar.training import LossTerms, fit, iteration_loss
from pig.config import load_preset, load_section
from pig.data.capture import Capture
from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import FactorizedSystem
from pig.field.latent_grid import FieldConfig
from pig.field.lattice_solve import LatticeSystem
from pig.field.precondition import PrecondConfig, PreconditionedTensor
from pig.render.api import RasterizerConfig
from op_names import OpNames
from preset_files import write_test_preset

WORLD = 2
# The one step of the parity test: 3 timesteps x 2 views, so that one timestep's views fall to both ranks; the LPIPS
# term (random weights) in MMLPHuman's form, on 4 of the 6 views drawn at random, with random windows.
STEP_FIT = dict(timesteps=3, views=2, weight_lpips=2.0, lpips_weights="random", lpips_net="alex", lpips_form="mmlphuman",
                lpips_crop=32, lpips_views=4, lpips_patches_from=0.0, lpips_start=0.0)


@pytest.mark.parametrize("count", range(1, 25))
def test_split_pairs_disjoint_cover_and_balanced(count):
    for world in range(1, min(count, 8) + 1):
        parts = split_pairs(count, world)
        assert sorted(p for part in parts for p in part) == list(range(count))  # disjoint, and the whole batch
        assert max(map(len, parts)) - min(map(len, parts)) <= 1
    with pytest.raises(ValueError, match="cannot be split"):
        split_pairs(count, count + 1)


def test_shard_picks_pose_only_the_timesteps_their_views_need():
    cameras = [f"c{i}" for i in range(16)]
    picks = Picks(2, [(t, cameras[t:t + 4]) for t in (7, 3, 9, 0, 5)])  # the paper's 5 timesteps x 4 views
    pairs = [(t, c) for t, cams in picks.steps for c in cams]
    for world, timesteps in ((1, [5]), (2, [3, 3]), (4, [2, 2, 2, 2])):
        shares = [shard_picks(picks, r, world) for r in range(world)]
        assert [len(s.steps) for s in shares] == timesteps
        assert len({s.share.digest for s in shares}) == 1 and all(s.lod == 2 and s.share.total == 20 for s in shares)
        mine = [(s.steps[k][0], cam, position) for s in shares for k, cam, position in s.share.places]
        assert [(t, c) for t, c, _ in mine] == pairs and [p for *_, p in mine] == list(range(20))
        for s in shares:  # each place names a view of the rank's own picks
            assert all(cam in s.steps[k][1] for k, cam, _ in s.share.places)


def test_solve_owners_balance_the_paper_solves():
    # The `paper` preset's grid levels (16 features, 8..88 cells a side) and its anchors (KNN system: costed as the
    # costliest level), as SolveShards costs them.
    knn = FactorizedSystem(knn_laplacian(np.random.default_rng(0).normal(size=(50, 3)), 4), 8.0)
    tensors = [PreconditionedTensor(torch.zeros(16, r, r, r), LatticeSystem((r, r, r), 2.0), "substitute")
               for r in (8, 24, 40, 56, 72, 88)] + [PreconditionedTensor(torch.randn(50, 3), knn, "substitute")]
    costs = solve_costs(tensors)
    assert costs[5] == 16 * 88**3 * 3 * 88 and costs[6] == costs[5] and costs == sorted(costs)
    assert solve_owners(costs, 1) == [0] * len(costs)
    # 2 ranks: at most 54 % of the work each (the finest level, or the anchors, plus the next level); 4 and 8: no rank
    # more than the largest solve, the least possible.
    for world, most in ((2, 0.55 * sum(costs)), (4, costs[-1]), (8, costs[-1])):
        owners = solve_owners(costs, world)
        load = [sum(c for c, o in zip(costs, owners) if o == r) for r in range(world)]
        assert set(owners) == set(range(min(world, len(costs))))  # every rank owns some, while there are enough
        assert max(load) <= most and owners[5] != owners[6]


def _count_solves(model: torch.nn.Module) -> Counter:
    """Counts of the solves of `model`'s preconditioned tensors from now on, by "tensor name:slot"."""
    counts = Counter()

    def counted(solve, name):
        def solve_counted(b, slot=None):
            counts[f"{name}:{slot}"] += 1
            return solve(b, slot)
        return solve_counted

    for name, module in model.named_modules():
        if isinstance(module, PreconditionedTensor) and module.system is not None:
            module.system.solve = counted(module.system.solve, name)
    return counts


def _one_step(capture_dir: Path, preset_path: str, parallel: Parallel | None, device: str = "cpu", phase=None):
    """One iteration (0, at progress 0.5) of the preset's fit on `device`: loss terms, gradients, the weights after
    the step, the rank's share of the views and the solves it ran (with `fit.shard_solves` the owners'); through the
    fit's functions, the model built as the fit builds it. `phase`: the fit's phase hook (pig.avatar.training.fit)."""
    preset = load_preset(preset_path)
    fit_cfg = load_section(preset, "fit", FitConfig)
    precond = load_section(preset, "precond", PrecondConfig)
    capture = Capture.load(capture_dir, cache_mb=0)
    train = capture.split["train"]
    spec = {"avatar": asdict(load_section(preset, "avatar", AvatarConfig)), "field": asdict(load_section(preset, "field", FieldConfig)),
            "precond": asdict(precond), "body_model_npz": body_model_npz(capture_dir / "body_model.npz"),
            "params": asdict(capture.params.select([capture.frames.index(f) for f in train["frames"]])),
            "frame_ids": [int(f) for f in train["frames"]], "variant": "pig"}
    torch.manual_seed(0)
    model = build_avatar(spec).to(device)
    optimizers = build_optimizers(model, fit_cfg.lr_decoders, fit_cfg.lr_refine, precond)
    solves = _count_solves(model)
    background = torch.as_tensor(capture.background, dtype=torch.float32, device=device)
    loss = LossTerms(fit_cfg, background, lpips_term(fit_cfg, device)[0], False)
    loss.at(0, 0.5)
    raster = load_section(preset, "rasterizer", RasterizerConfig)
    seen_by = tuple(tuple(c for c in train["cameras"] if capture.has(c, f)) for f in train["frames"])
    sampler = Sampler(fit_cfg.seed, model.num_levels, seen_by, fit_cfg.timesteps, fit_cfg.views)
    if parallel is not None:
        sampler = ShardedSampler(sampler, parallel.rank, parallel.world)
    with ViewSource(capture, train["frames"], device, 0, 1) as source:
        batch = TrainingBatches(source, sampler, 1, 0).get(0)
    phase = phase or (lambda name: nullcontext())
    if parallel is None:
        terms = iteration_loss(model, batch, loss, raster, background, True, phase)
    else:
        reducer = GradientReducer(list(model.parameters()), bucket_mb=0.01)  # several buckets
        shards = SolveShards(model, parallel.rank, parallel.world) if fit_cfg.shard_solves else None
        if shards is not None:
            shards.solve_forward()
        terms = shard_loss(model, batch, loss, raster, background, phase, parallel)
    terms["total"].backward()
    if parallel is not None:
        reducer.finish()
        if shards is not None:
            shards.solve_backward()
        terms = parallel.sum_terms(terms)
    grads = {name: p.grad.cpu() for name, p in model.named_parameters()}
    for opt in optimizers:
        opt.step()
    return ({k: v.detach().cpu() for k, v in terms.items()}, grads, {k: v.detach().cpu() for k, v in model.state_dict().items()},
            batch.share, dict(solves))


def _step_rank(rank: int, port: int, capture_dir: str, preset_path: str, out: str, device_type: str = "cpu") -> None:
    """One rank of the parity step: gloo on the CPU, or NCCL on cuda:rank with gloo for the decisions (as a fit)."""
    timeout = timedelta(seconds=120)
    store = dist.TCPStore("127.0.0.1", port, WORLD, is_master=False, timeout=timeout)
    device = torch.device("cuda", rank) if device_type == "cuda" else torch.device("cpu")
    if device_type == "cuda":
        torch.cuda.set_device(device)
        dist.init_process_group("nccl", store=store, rank=rank, world_size=WORLD, timeout=timeout, device_id=device)
        control = dist.new_group(backend="gloo", timeout=timeout)
    else:
        dist.init_process_group("gloo", store=store, rank=rank, world_size=WORLD, timeout=timeout)
        control = dist.group.WORLD
    torch.set_num_threads(1)
    try:
        parallel = Parallel(rank, WORLD, device, control)
        result = _one_step(Path(capture_dir), preset_path, parallel, str(device))
        # Rank 0's decisions reach every rank; a rank whose picks differ from rank 0's is stopped.
        decided = parallel.decide(rank == 1, 0.25 * (rank + 1), result[3].digest, 0)
        try:
            parallel.decide(False, 0.0, result[3].digest + rank, 1)
            refused = ""
        except RuntimeError as err:
            refused = str(err)
        torch.save(result[:3] + (asdict(result[3]), decided, refused, result[4]), Path(out) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize("shard_solves", [False, True])
def test_two_gloo_processes_compute_the_one_process_step(small_capture, tmp_path, shard_solves):
    preset = write_test_preset(tmp_path, **STEP_FIT, shard_solves=shard_solves)
    store = dist.TCPStore("127.0.0.1", 0, WORLD, is_master=True, wait_for_workers=False)
    start_processes(_step_rank, args=(store.port, str(small_capture), preset, str(tmp_path)), nprocs=WORLD,
                    start_method="spawn")
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in range(WORLD)]
    terms, grads, weights, _, solves = _one_step(small_capture, preset, None)

    # The solves: one process solves each preconditioned tensor once forward and once backward; two ranks each solve
    # every one (their own part of the gradient), or with the solves sharded each solve runs on one rank alone.
    assert len(solves) >= 4 and set(solves.values()) == {1}  # grid levels and anchors, forward and backward
    ran = [rank[6] for rank in ranks]
    runs_of = {key: sum(r.get(key, 0) for r in ran) for key in solves}
    assert runs_of == {key: 1 if shard_solves else WORLD for key in solves}
    assert set(ran[0]) | set(ran[1]) == set(solves)
    if shard_solves:  # both ranks own some, each a tensor whole (forward and backward)
        owned = [{key.rsplit(":", 1)[0] for key in r} for r in ran]
        assert all(owned) and not owned[0] & owned[1]

    places = [tuple(place[2] for place in rank[3]["places"]) for rank in ranks]
    assert [rank[4] for rank in ranks] == [(False, 0.25)] * 2  # rank 0's decisions, whatever rank 1 measured
    assert ranks[0][5] == "" and "rank 1 drew other views than rank 0 at iteration 1" in ranks[1][5]
    assert sorted(places[0] + places[1]) == list(range(6)) and all(places)  # disjoint, together the whole batch
    assert {k: float(v) for k, v in ranks[0][0].items()} == {k: float(v) for k, v in ranks[1][0].items()}
    assert set(ranks[0][0]) == set(terms) and terms["lpips"] > 0
    for key in terms:  # the iteration's loss: each rank's part, summed
        torch.testing.assert_close(ranks[0][0][key], terms[key], rtol=1e-5, atol=1e-7)
    # The summed gradients against the one-process ones, within float32 rounding: each rank sums its own views'
    # contributions and the two sums are added, where one process adds them in another order, and the LPIPS
    # network and the renders run on batches of other sizes (other blockings of their sums). Each such difference is
    # a few units in the last place (2^-24 ~ 6e-8) of the terms summed; through the backward they added up to at
    # most 2.8e-6 of a tensor's largest gradient (measured, CPU). Tolerance 3e-5 of it: 10x that, while a view lost
    # or counted twice (a sixth of the batch) moves gradients by ~1e-1 of it.
    # With the solves sharded the backward solves the summed gradient once, as one process does, instead of adding
    # two ranks' solves: the same bound holds (measured: 1.6e-6 for the anchors against 1.7e-6, 2.8e-6 overall).
    for name, reference in grads.items():
        assert torch.equal(ranks[0][1][name], ranks[1][1][name]), name
        scale = reference.abs().max().item()
        torch.testing.assert_close(ranks[0][1][name], reference, rtol=0, atol=3e-5 * scale, msg=name)
    differences = {name: ((ranks[0][1][name] - g).abs().max() / g.abs().max()).item() for name, g in grads.items()
                   if g.abs().max() > 0}
    preconditioned = {key.rsplit(":", 1)[0] + ".param" for key in solves}
    print(f"shard_solves={shard_solves}: loss {terms['total']:.8f} (1 process) {ranks[0][0]['total']:.8f} (2); largest "
          f"gradient difference / tensor's largest gradient {max(differences.values()):.2e}, preconditioned tensors: "
          + ", ".join(f"{name} {differences[name]:.2e}" for name in sorted(preconditioned))
          + f"; solves per rank {ran}")  # what NOTES records (pytest -rP shows it)
    assert any(grads[name].abs().max() > 0 for name in grads if name.startswith("refiner"))
    for name, value in weights.items():  # after the step: identical on every rank, and the one-process step's
        assert torch.equal(ranks[0][2][name], ranks[1][2][name]), name
        if value.is_floating_point():
            torch.testing.assert_close(ranks[0][2][name], value, rtol=1e-4, atol=1e-6, msg=name)


class _BlockingCopies(TorchFunctionMode):
    """Records, while active, the calls that copy host data to a GPU with a blocking copy, which waits for the
    device's queue to drain (a host synchronisation): a tensor made from host data (torch.tensor, torch.as_tensor,
    torch.from_numpy) on a named device, or such a tensor moved by .to, .cuda or copy_ without non_blocking=True.
    On the CPU those copies do nothing, but the calls are those a GPU fit makes."""

    MAKERS = ("tensor", "as_tensor", "from_numpy")

    def __init__(self):
        super().__init__()
        self.host: dict[int, torch.Tensor] = {}  # made from host data, not yet copied without blocking
        self.blocking: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = getattr(func, "__name__", "")
        non_blocking = kwargs.get("non_blocking") is True or any(a is True for a in args[1:])
        if name in self.MAKERS and args and not isinstance(args[0], torch.Tensor):
            if kwargs.get("device") is not None:
                self.blocking.append(f"torch.{name}(..., device=...)")
            else:
                self.host[id(out)] = out
        elif name in ("to", "cuda") and args and id(args[0]) in self.host:
            if not non_blocking:
                self.blocking.append(f"Tensor.{name} of host data")
            self.host.pop(id(args[0]))
        elif name == "copy_" and len(args) > 1 and id(args[1]) in self.host and not non_blocking:
            self.blocking.append("Tensor.copy_ of host data")
        return out


def test_the_step_copies_no_host_data_to_the_device_blocking(small_capture, tmp_path):
    # The model's forward in a step, one process and a data-parallel rank: the timesteps went to the model as a host
    # tensor that it moved to the device, and the decoders made their identity quaternion from a list on the device,
    # each a blocking copy on a GPU, two host synchronisations a step (benchmarks/NOTES.md, "the host's share").
    preset = write_test_preset(tmp_path, **STEP_FIT)
    recorded = []

    @contextmanager
    def phase(name):
        if name != "model":
            yield
            return
        with _BlockingCopies() as mode:
            yield
        recorded.append(mode.blocking)

    _one_step(small_capture, preset, None, phase=phase)
    store = dist.TCPStore("127.0.0.1", 0, 1, is_master=True, timeout=timedelta(seconds=60))
    dist.init_process_group("gloo", store=store, rank=0, world_size=1)
    try:
        _one_step(small_capture, preset, Parallel(0, 1, torch.device("cpu"), dist.group.WORLD), phase=phase)
    finally:
        dist.destroy_process_group()
    assert recorded == [[], []]


def test_gradient_reducer_writes_the_sums_back_in_one_copy_per_bucket():
    # `finish` wrote each parameter's summed gradient back with a copy of its own: on a GPU a kernel launch per
    # parameter (39 in the `paper` avatar) on every rank every step, whatever its share of the views.
    torch.manual_seed(0)
    net = torch.nn.Sequential(*[torch.nn.Linear(4, 4) for _ in range(10)])
    store = dist.TCPStore("127.0.0.1", 0, 1, is_master=True, timeout=timedelta(seconds=60))
    dist.init_process_group("gloo", store=store, rank=0, world_size=1)
    try:
        reducer = GradientReducer(list(net.parameters()), bucket_mb=0.0003)  # buckets of at most 314 bytes
        net(torch.randn(3, 4)).square().sum().backward()
        own = [p.grad.clone() for p in net.parameters()]
        with OpNames() as ops:
            reducer.finish()
        reducer.close()
    finally:
        dist.destroy_process_group()
    assert len(reducer.buckets) == 3 and len(own) == 20  # 80 bytes a layer: 7, 7 and 6 parameters
    assert ops.names["copy_"] == 0 and ops.names["_foreach_copy_"] == 3
    for p, grad in zip(net.parameters(), own):  # one process: the sum is its own gradient, written back
        assert torch.equal(p.grad, grad)


class _FakeClock:
    """A clock that advances `step_s` seconds at each reading (no real time is read)."""

    def __init__(self, step_s: float):
        self.now, self.step_s = 0.0, step_s

    def __call__(self) -> float:
        self.now += self.step_s
        return self.now


class _Record:
    """Writes the iterations a rank finished to `folder`/rank{r}.txt."""

    def __init__(self, folder: str, rank: int):
        self.path = Path(folder) / f"rank{rank}.txt"

    def __call__(self, iteration: int) -> None:
        with open(self.path, "a") as file:
            file.write(f"{iteration}\n")


def _skewed(folder: str, rank: int) -> RankHooks:
    # Rank 1's clock runs 400 times as fast: on its own it would stop at once and save at every iteration.
    return RankHooks(clock=_FakeClock(0.25 if rank == 0 else 100.0), on_iteration=_Record(folder, rank))


def _iterations(folder: Path, rank: int) -> list[int]:
    return [int(line) for line in (folder / f"rank{rank}.txt").read_text().split()]


def _log(output: Path) -> list[dict]:
    with open(output / "train_log.csv", newline="") as file:
        return list(csv.DictReader(file))


@pytest.mark.parametrize("levers", [
    pytest.param({}, id="per-timestep"),
    # The `paper` preset's path in float32: one rasterizer call and one loss for all of an iteration's views in one
    # process (the ranks render and score theirs), the silhouette band from the loader, the LPIPS term over every
    # view with random windows from the third iteration on, the anchors' CG solves (which 8 steps at the anchors'
    # rate, 2e-5, barely feel: a misordered batched loss fails this case, a CG tolerance of 0.3 does not).
    pytest.param({"fit": dict(batched_render=True, host_band=True, lpips_views=0, lpips_patches_from=0.375),
                  "precond": dict(knn_solver="cg", cg_check_every=8)}, id="batched"),
])
def test_two_processes_follow_the_one_process_fit_step_after_step(small_capture, tmp_path, levers, capfd):
    # A whole fit, not one step: 8 iterations of the parity step's batch with the LPIPS term on random views, one
    # process against `pig fit --gpus 2` on the CPU. On the CPU a fit is bit-identical run to run, so the two differ
    # by the order of their sums alone: measured <= 1.4e-6 relative on every step's loss over 300 steps per timestep
    # and <= 7.3e-7 over 200 batched (benchmarks/parity_trajectory.py), where one view more or less in the LPIPS term
    # moved the first step's loss by 4.5e-4 (the bug this found, per timestep). Bound 1e-5.
    preset = write_test_preset(tmp_path, precond=levers.get("precond"), **{**STEP_FIT, **levers.get("fit", {})},
                               iterations=8, eval_every=8, log_every=1)
    one, two = tmp_path / "one", tmp_path / "two"
    fit(small_capture, one, preset, threads=1, progress_s=1e6)
    capfd.readouterr()
    fit_parallel(small_capture, two, preset, "pig", WORLD, "cpu", progress_s=1e6, cores=2, timeout_s=120)
    assert capfd.readouterr().err.count("LPIPS term with randomly initialised") == 1  # rank 0 tells, not each rank
    rows = [{int(r["iteration"]): r for r in _log(folder)} for folder in (one, two)]
    assert sorted(rows[0]) == sorted(rows[1]) == list(range(9))
    for i in range(1, 9):
        a, b = (float(r[i]["loss"]) for r in rows)
        assert abs(b - a) <= 1e-5 * a, (i, a, b)
        assert rows[0][i]["lod"] == rows[1][i]["lod"]
    assert float(rows[1][8]["lpips"]) > 0
    assert abs(float(rows[1][8]["heldout_psnr"]) - float(rows[0][8]["heldout_psnr"])) < 1e-3


def test_rank_zero_clock_decides_budget_schedule_and_checkpoints(small_capture, tmp_path):
    # A time budget with a decaying learning rate (the run's progress is its time fraction), a checkpoint each
    # 2 s of rank 0's clock: were any decided by rank 1's own clock, the ranks would run different iterations or
    # step different rates (their weights differ: the fit's replica check raises) or meet at different collectives.
    # With the solves sharded (fit.shard_solves), which adds a collective before the forward and after the reduce,
    # while rank 0's closing evaluation must solve alone.
    preset = write_test_preset(tmp_path, iterations=1000, time_budget_s=6.0, lr_final=0.1, checkpoint_minutes=2 / 60,
                               eval_every=10**6, log_every=1, shard_solves=True)
    fit_parallel(small_capture, tmp_path / "out", preset, "pig", WORLD, "cpu", progress_s=1e6,
                 rank_hooks=functools.partial(_skewed, str(tmp_path)), timeout_s=120)
    done = [_iterations(tmp_path, r) for r in range(WORLD)]
    assert done[0] == done[1] and 2 < len(done[0]) < 1000  # stopped by the budget, on rank 0's clock, together
    rows = _log(tmp_path / "out")
    assert int(rows[-1]["iteration"]) == done[0][-1] and (tmp_path / "out" / "avatar.pt").exists()
    assert not (tmp_path / "out" / "checkpoint.pt").exists()


class Killed(Exception):
    pass


class _Kill:
    """Stops the fit after iteration `at`, as a kill would (the checkpoint of that iteration is written)."""

    def __init__(self, at: int):
        self.at = at

    def __call__(self, iteration: int) -> None:
        if iteration == self.at:
            raise Killed(f"killed after iteration {iteration}")


def _kill_rank0(at: int, rank: int) -> RankHooks:
    return RankHooks(on_iteration=_Kill(at) if rank == 0 else None)


def test_resume_across_process_counts(small_capture, tmp_path):
    # One process killed after iteration 2, two resume it and are killed after 4, one finishes at 6: each resume
    # continues the same log from the last checkpoint (written after every iteration here).
    preset = write_test_preset(tmp_path, iterations=6, eval_every=10**6, checkpoint_minutes=0.0, log_every=1)
    out = tmp_path / "out"
    with pytest.raises(Killed):
        fit(small_capture, out, preset, on_iteration=_Kill(2), progress_s=1e6)
    with pytest.raises(RuntimeError, match="rank 0 of 2"):
        fit_parallel(small_capture, out, preset, "pig", WORLD, "cpu", progress_s=1e6,
                     rank_hooks=functools.partial(_kill_rank0, 4), timeout_s=120)
    assert [int(r["iteration"]) for r in _log(out)] == [0, 1, 2, 3, 4]  # the last checkpoint's rows
    fit(small_capture, out, preset, progress_s=1e6)
    assert [int(r["iteration"]) for r in _log(out)] == list(range(7))
    assert not (out / "checkpoint.pt").exists() and (out / "avatar.pt").exists()


class _WriteOnce:
    """Writes `value()` of this rank to `folder`/{name}{rank} after its first iteration."""

    def __init__(self, name: str, value, folder: str, rank: int):
        self.path, self.value = Path(folder) / f"{name}{rank}", value

    def __call__(self, iteration: int) -> None:
        if not self.path.exists():
            self.path.write_text(str(self.value()))


def _pid_hooks(folder: str, rank: int) -> RankHooks:
    """Each rank writes its process id to `folder`/pid{rank}."""
    return RankHooks(on_iteration=_WriteOnce("pid", os.getpid, folder, rank))


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as file:
            return file.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


def _wait_until(condition, limit_s: float) -> bool:
    """Polls `condition` until it holds or `limit_s` passed (a limit, not a measurement)."""
    end = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.2)
    return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_ranks_end_with_the_process_that_started_them(small_capture, tmp_path):
    # The starting process killed (SIGKILL: no handler runs) mid-fit: its ranks must not fit on as orphans, holding
    # the devices while a rerun takes the output folder (torch's spawn asks the kernel to send them SIGINT then).
    preset = write_test_preset(tmp_path, iterations=10**6, eval_every=10**6)
    script = tmp_path / "start.py"
    script.write_text(textwrap.dedent(f"""
        import functools, sys
        sys.path[:0] = {[str(Path(__file__).parent), *sys.path]!r}
        from test_fit_parallel import _pid_hooks
        from pig.avatar.parallel_fit import fit_parallel
        if __name__ == "__main__":
            fit_parallel({str(small_capture)!r}, {str(tmp_path / "out")!r}, {preset!r}, "pig", 2, "cpu", progress_s=1e6,
                         rank_hooks=functools.partial(_pid_hooks, {str(tmp_path)!r}))
    """))
    starter = subprocess.Popen([sys.executable, str(script)], env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    pids = [tmp_path / f"pid{rank}" for rank in range(WORLD)]
    try:
        assert _wait_until(lambda: all(p.exists() for p in pids) or starter.poll() is not None, 300)
        assert starter.poll() is None, "the fit ended before it was killed"
        ranks = [int(p.read_text()) for p in pids]
        starter.kill()
        starter.wait()
        assert _wait_until(lambda: not any(map(_running, ranks)), 60), "a rank outlived the process that started it"
    finally:
        if starter.poll() is None:
            starter.kill()
        for p in pids:  # what this test started, should it have outlived the test
            if p.exists() and _running(int(p.read_text())):
                os.kill(int(p.read_text()), signal.SIGKILL)


def _thread_hooks(folder: str, rank: int) -> RankHooks:
    """Each rank writes its torch intra-op threads to `folder`/threads{rank}."""
    return RankHooks(on_iteration=_WriteOnce("threads", torch.get_num_threads, folder, rank))


def test_each_rank_takes_its_share_of_the_cores(small_capture, tmp_path, monkeypatch):
    # Torch's default, a thread per core in each rank, oversubscribes a host N-fold: each rank takes the host's
    # cores divided by the ranks (at least 1), or those of `cores` (pig fit --gpus N --threads T: the job's).
    assert [rank_threads(4, 64), rank_threads(3, 64), rank_threads(8, 4)] == [16, 21, 1]
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)  # which torch would read, and the default leaves alone
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    for name, given, expected in (("default", None, max(1, cores // WORLD)), ("given", 6, 3)):
        folder = tmp_path / name
        folder.mkdir()
        preset = write_test_preset(folder, iterations=1, eval_every=10**6, cpu_threads=0)  # the preset's setting: none
        fit_parallel(small_capture, folder / "out", preset, "pig", WORLD, "cpu", progress_s=1e6, timeout_s=120,
                     rank_hooks=functools.partial(_thread_hooks, str(folder)), cores=given)
        assert [int((folder / f"threads{rank}").read_text()) for rank in range(WORLD)] == [expected] * WORLD, name
    with pytest.raises(ValueError, match="cores must be at least 1"):
        fit_parallel(small_capture, tmp_path / "none", preset, "pig", WORLD, "cpu", cores=0)


def _placement():
    """This rank's CPUs, torch threads and OpenCV threads, as text."""
    import cv2

    return repr((sorted(os.sched_getaffinity(0)), torch.get_num_threads(), cv2.getNumThreads()))


def _placement_hooks(folder: str, rank: int) -> RankHooks:
    return RankHooks(on_iteration=_WriteOnce("placement", _placement, folder, rank))


def test_rank_cpu_sets_are_disjoint_balanced_and_local_first():
    assert rank_cpu_sets(4, list(range(64))) == [list(range(16 * r, 16 * r + 16)) for r in range(4)]
    sets = rank_cpu_sets(3, [0, 1, 2, 3, 4, 5, 6, 9])  # 8 CPUs, 3 ranks: 3 + 3 + 2, every one used once
    assert sorted(cpu for s in sets for cpu in s) == [0, 1, 2, 3, 4, 5, 6, 9] and [len(s) for s in sets] == [3, 3, 2]
    # Two NUMA nodes of 8, GPUs 0-1 on the second, 2-3 on the first: each rank takes its GPU's node.
    second, first = set(range(8, 16)), set(range(8))
    assert rank_cpu_sets(4, list(range(16)), [second, second, first, first]) == [
        [8, 9, 10, 11], [12, 13, 14, 15], [0, 1, 2, 3], [4, 5, 6, 7]]
    # A node with fewer CPUs than its ranks need lends the rest from the others; unknown locality is no preference.
    assert rank_cpu_sets(2, [0, 1, 2, 3], [{0}, None]) == [[0, 1], [2, 3]]
    assert rank_cpu_sets(2, [0, 1, 2, 3], [{3}, {3}]) == [[0, 3], [1, 2]]
    with pytest.raises(ValueError, match="a CPU a rank"):
        rank_cpu_sets(3, [0, 1])


def test_a_physical_cores_hardware_threads_go_to_one_rank(tmp_path):
    # 4 cores of 2 threads numbered as Linux often does: CPU n and n + 4 share a core.
    for cpu in range(8):
        (tmp_path / f"cpu{cpu}" / "topology").mkdir(parents=True)
        (tmp_path / f"cpu{cpu}" / "topology" / "thread_siblings_list").write_text(f"{cpu % 4},{cpu % 4 + 4}\n")
    cores = core_of(list(range(9)), tmp_path)  # cpu8: no topology, its own core
    assert cores == {0: 0, 1: 1, 2: 2, 3: 3, 4: 0, 5: 1, 6: 2, 7: 3, 8: 8}
    assert rank_cpu_sets(2, list(range(8)), cores=cores) == [[0, 1, 4, 5], [2, 3, 6, 7]]
    node = set(range(8))  # one NUMA node, both GPUs on it: the cores still go whole
    assert rank_cpu_sets(2, list(range(8)), [node, node], cores) == [[0, 1, 4, 5], [2, 3, 6, 7]]
    assert rank_cpu_sets(2, list(range(8))) == [[0, 1, 2, 3], [4, 5, 6, 7]]  # without the topology: by number


def test_gpu_local_cpus_reads_the_devices_numa_node(tmp_path, monkeypatch):
    assert parse_cpu_list("0-3,8,10-11\n") == {0, 1, 2, 3, 8, 10, 11}
    device = tmp_path / "0000:1b:00.0"
    device.mkdir()
    (device / "local_cpulist").write_text("32-63\n")
    props = type("Props", (), {"pci_bus_id": 0x1B, "pci_device_id": 0, "pci_domain_id": 0})
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda index: props)
    assert gpu_local_cpus(0, tmp_path) == set(range(32, 64))
    props.pci_bus_id = 0x3C  # no such device: no preference
    assert gpu_local_cpus(0, tmp_path) is None
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda index: object())  # a torch that does not tell
    assert gpu_local_cpus(0, tmp_path) is None


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU affinity is Linux's")
def test_pinned_ranks_run_on_their_own_cpus(small_capture, tmp_path, capsys):
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < WORLD:
        pytest.skip(f"{WORLD} ranks need {WORLD} CPUs")
    preset = write_test_preset(tmp_path, iterations=1, eval_every=10**6, cpu_threads=0)
    fit_parallel(small_capture, tmp_path / "out", preset, "pig", WORLD, "cpu", progress_s=1e6, timeout_s=120,
                 rank_hooks=functools.partial(_placement_hooks, str(tmp_path)), pin_cpus=True)
    placed = [ast.literal_eval((tmp_path / f"placement{rank}").read_text()) for rank in range(WORLD)]
    assert [cpus for cpus, _, _ in placed] == rank_cpu_sets(WORLD, allowed)
    assert all(threads == opencv == len(cpus) for cpus, threads, opencv in placed)
    assert sorted(os.sched_getaffinity(0)) == allowed  # the starting process stays where it was

    from pig.stages.fit import main

    with pytest.raises(SystemExit):
        main(["--capture", str(small_capture), "--output", str(tmp_path / "o"), "--pin-cpus"])
    assert "--pin-cpus shares the cores out" in capsys.readouterr().err


def test_fit_stage_gpus_option(small_capture, tmp_path, capsys):
    from pig.stages.fit import main

    with pytest.raises(SystemExit):
        main(["--capture", str(small_capture), "--output", str(tmp_path / "o"), "--gpus", "2", "--device", "cpu"])
    assert "--device cpu cannot go with it" in capsys.readouterr().err
    if torch.cuda.device_count() < 2:
        with pytest.raises(ValueError, match="CUDA device"):
            main(["--capture", str(small_capture), "--output", str(tmp_path / "o"), "--gpus", "2"])
        assert not (tmp_path / "o").exists()  # refused before anything was written
