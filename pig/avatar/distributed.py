"""Data-parallel fitting: one avatar on several GPUs at once, one process per device (torch.distributed).

Every process (rank) holds the whole avatar and its optimisers and computes the same iteration as one process
would, on its part of the iteration's views:
- The split: the iteration's (timestep, camera) pairs, in the sampler's order (timesteps, then each timestep's
  cameras), cut into `world` consecutive runs whose lengths differ by at most one (`split_pairs`). A rank decodes,
  poses and renders only the timesteps of its run: with the paper's 5 timesteps x 4 views, 2 ranks take 10 views
  of 3 timesteps each and 4 ranks 5 views of 2 timesteps each. Its view loader stages only those views.
- The math: every term of Eq. 15 is a mean over the iteration's views; a rank computes its views' part of it (their
  sum over the iteration's count, `LossShare`), so the ranks' losses sum to the one-process loss and their
  gradients are summed (`GradientReducer`: all-reduce in buckets, launched during the backward as the buckets
  fill). The LPIPS term's crops: its random views and windows are drawn for the whole iteration from (seed,
  iteration), as one process draws them, and each rank takes its own; the "mmlphuman" form's divisor (the views
  with a mask) is summed over the ranks. The preconditioned updates (Eqs. 4-5) are linear in the gradient, so
  every rank solves its part and the sum is the one-process solve; the optimisers then step identical gradients
  on every rank, which keeps the weights identical (checked at the start, at each checkpoint and at the end:
  `Parallel.check_replicas`).
- The solves, sharded (`fit.shard_solves`, `SolveShards`): every rank solving every preconditioned tensor, forward
  and backward, is work that N ranks repeat (the grid's DCT solves and the anchors' CG, ~10 ms of the `paper` step
  on an H100). Instead each tensor has one owner rank (`solve_owners`): the owner solves the forward offset
  A^-1 u and broadcasts it; the backward passes the raw dL/dx, which the GradientReducer sums as any gradient; the
  owner solves A^-1 of the sum and broadcasts that. The one-process math again (the solve is linear), each solve
  run once per step.
- Decisions: what reads a clock (the time budget, the learning-rate schedule's progress, the checkpoint cadence)
  is decided by rank 0 and broadcast (`Parallel.shared`); the batch sample and the LOD come from (seed,
  iteration) on every rank and rank 0's digest of them is checked. Rank 0 alone evaluates, logs, writes
  checkpoints and avatar.pt; any rank resumes from a checkpoint written by any number of ranks.

One process (the default) runs none of this: no all-reduce, no broadcast. The processes are started by
pig.avatar.parallel_fit.
"""
from __future__ import annotations

import time
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
import torch.distributed as dist

from pig.avatar.batches import Picks, Sampler, TrainingBatch, ViewShare, host_to_device
from pig.field.lattice_solve import LatticeSystem
from pig.field.precondition import PreconditionedTensor
from pig.render.api import render_timesteps

DEFAULT_BUCKET_MB = 25.0  # gradients all-reduced in buckets of about this size, as DistributedDataParallel's default


def split_pairs(count: int, world: int) -> list[range]:
    """The pairs (positions 0..count-1) of each of `world` ranks: consecutive runs, lengths differing by at most 1."""
    if not 1 <= world <= count:
        raise ValueError(f"split_pairs: {count} views cannot be split over {world} processes (each needs one)")
    return [range(r * count // world, (r + 1) * count // world) for r in range(world)]


def shard_picks(picks: Picks, rank: int, world: int) -> Picks:
    """Rank `rank`'s part of an iteration's `picks` (split_pairs of the places of Picks.whole), with its ViewShare."""
    whole = picks.whole()
    mine = split_pairs(whole.total, world)[rank]
    steps: list[tuple[int, list[str]]] = []
    places = []
    for k, cam, position in whole.places[mine.start:mine.stop]:
        step = picks.steps[k][0]
        if not steps or steps[-1][0] != step:
            steps.append((step, []))
        steps[-1][1].append(cam)
        places.append((len(steps) - 1, cam, position))
    return Picks(picks.lod, steps, ViewShare(tuple(places), whole.total, whole.digest))


@dataclass(frozen=True)
class ShardedSampler:
    """A Sampler's picks, each cut to this rank's part."""

    sampler: Sampler
    rank: int
    world: int

    def picks(self, iteration: int) -> Picks:
        return shard_picks(self.sampler.picks(iteration), self.rank, self.world)


class SummedCount:
    """A device scalar being summed over the ranks by an asynchronous all-reduce; calling it waits for the sum (on a
    GPU the device waits, from then on in the stream, not the host) and returns it."""

    def __init__(self, total: torch.Tensor, work: dist.Work):
        self._total, self._work = total, work

    def __call__(self) -> torch.Tensor:
        if self._work is not None:
            self._work.wait()
            self._work = None
        return self._total[0]


@dataclass
class LossShare:
    """What a loss evaluation of some of an iteration's views needs to compute their part of the iteration's loss
    (pig.avatar.training.LossTerms): their share of the views, the rows among them that the LPIPS term sees (None:
    all), those rows' windows, and the LPIPS term's divisor over the whole iteration."""

    weight: float
    lpips_rows: np.ndarray | None
    lpips_offsets: np.ndarray | None
    lpips_count: "SummedCount | float | None"


class GradientReducer:
    """Sums the gradients of `params` over the ranks of the default process group during the backward.

    The parameters are cut into buckets of about `bucket_mb`, in reverse order (the backward's order, roughly); a
    bucket is flattened and all-reduced asynchronously as soon as its last gradient is accumulated and the buckets
    before it are launched, so that every rank launches the same collectives in the same order. `finish` (after
    `backward`) launches what remains, waits, and writes the sums back. A parameter without a gradient on a rank
    counts as zero there and gets the sum (zero where no rank had one: every rank runs the whole avatar forward,
    so a parameter that no rank's loss reaches is one that no iteration reaches, and Adam leaves it where it is
    from zero gradients as it does without any).
    """

    def __init__(self, params: list[torch.nn.Parameter], bucket_mb: float = DEFAULT_BUCKET_MB):
        params = [p for p in params if p.requires_grad]
        self.buckets: list[list[torch.nn.Parameter]] = []
        size = 0.0
        for p in reversed(params):
            if (not self.buckets or size + p.numel() * p.element_size() > bucket_mb * 2**20
                    or p.dtype != self.buckets[-1][-1].dtype):
                self.buckets.append([])
                size = 0.0
            self.buckets[-1].append(p)
            size += p.numel() * p.element_size()
        self._bucket_of = {p: b for b, bucket in enumerate(self.buckets) for p in bucket}
        self._hooks = [p.register_post_accumulate_grad_hook(self._ready) for p in params]
        self._reset()

    @property
    def bucket_bytes(self) -> list[int]:
        """The bytes each bucket all-reduces per step, in launch order."""
        return [sum(p.numel() * p.element_size() for p in bucket) for bucket in self.buckets]

    def _reset(self) -> None:
        self._waiting = [len(bucket) for bucket in self.buckets]
        self._launched: list[tuple[torch.Tensor, dist.Work]] = []

    def _ready(self, param: torch.nn.Parameter) -> None:
        bucket = self._bucket_of[param]
        self._waiting[bucket] -= 1
        while len(self._launched) < len(self.buckets) and self._waiting[len(self._launched)] == 0:
            self._launch(len(self._launched))

    def _launch(self, bucket: int) -> None:
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in self.buckets[bucket]])
        self._launched.append((flat, dist.all_reduce(flat, async_op=True)))

    def finish(self) -> None:
        """Launch the buckets not yet launched, wait for all, and give each parameter the sum of its gradients."""
        for bucket in range(len(self._launched), len(self.buckets)):
            self._launch(bucket)
        for bucket, (flat, work) in zip(self.buckets, self._launched):
            work.wait()
            parts = [part.view_as(p) for p, part in zip(bucket, flat.split([p.numel() for p in bucket]))]
            held = [(p.grad, part) for p, part in zip(bucket, parts) if p.grad is not None]
            if held:  # one multi-tensor copy, not a kernel launch per parameter
                torch._foreach_copy_([grad for grad, _ in held], [part for _, part in held])
            for p, part in zip(bucket, parts):
                if p.grad is None:
                    p.grad = part.clone()
        self._reset()

    def close(self) -> None:
        for hook in self._hooks:
            hook.remove()


def _untimed(name: str) -> AbstractContextManager:
    return nullcontext()


def solve_costs(tensors: list[PreconditionedTensor]) -> list[float]:
    """Each tensor's solve, in relative units, to balance the ranks' shares: a grid level's DCT solve does sum(shape)
    multiply-adds per value and transform (pig.field.lattice_solve); any other system (the anchors' KNN solve)
    counts as the costliest grid level (on an H100 the `paper` preset's CG took 3.4 ms, forward + backward, against
    ~3.8 ms for the finest level's part of the DCT solves' 6.3: benchmarks/NOTES.md, runs 17-18)."""
    lattice = {id(t): float(t.param.numel() * sum(t.system.shape)) for t in tensors
               if isinstance(t.system, LatticeSystem)}
    other = max(lattice.values(), default=1.0)
    return [lattice.get(id(t), other) for t in tensors]


def solve_owners(costs: list[float], world: int) -> list[int]:
    """The rank that solves each of the tensors of `costs`: the costliest first, each to the rank with the least
    cost so far (the lowest rank on a tie). The same costs give the same owners on every rank."""
    load = [0.0] * world
    owners = [0] * len(costs)
    for index in sorted(range(len(costs)), key=lambda i: (-costs[i], i)):
        owners[index] = min(range(world), key=lambda r: (load[r], r))
        load[owners[index]] += costs[index]
    return owners


class SolveShards:
    """The preconditioned tensors' solves of a data-parallel step (Eqs. 4-5), each run by one rank, its owner.

    `solve_forward` (before the forward): each owner solves its tensors' offsets A^-1 u and broadcasts them; the
    tensors' forward returns them (PreconditionedTensor.give). Their backward leaves dL/dx unsolved
    (`defer_gradient`), summed over the ranks by the GradientReducer. `solve_backward` (after GradientReducer.finish,
    before the optimisers step): each owner replaces its tensors' summed gradients by the preconditioned ones and
    broadcasts them. Every rank calls both, in step, with the same model: the broadcasts follow the tensors' order.
    The owners solve before any broadcast is launched, so that the ranks solve at the same time."""

    def __init__(self, model: torch.nn.Module, rank: int, world: int):
        self.rank = rank
        tensors = [m for m in model.modules() if isinstance(m, PreconditionedTensor) and m.form != "none"]
        self.shares = list(zip(tensors, solve_owners(solve_costs(tensors), world)))  # (tensor, its owner)
        for tensor in tensors:
            tensor.defer_gradient = True

    def solve_forward(self, phase: Callable[[str], AbstractContextManager] | None = None) -> None:
        """Every substitution-form tensor's offset for its current u, solved by its owner, given to its next forward.
        `phase` (a profiler's hook) times this rank's own solves as "solve_forward.own"."""
        shared = [(t, owner) for t, owner in self.shares if t.form == "substitute"]
        with (phase or _untimed)("solve_forward.own"):
            offsets = [t.solve_offset().contiguous() if owner == self.rank else torch.empty_like(t.param)
                       for t, owner in shared]
        works = [dist.broadcast(offset, owner, async_op=True) for offset, (_, owner) in zip(offsets, shared)]
        for work, offset, (tensor, _) in zip(works, offsets, shared):
            work.wait()
            tensor.give(offset)

    def solve_backward(self, phase: Callable[[str], AbstractContextManager] | None = None) -> None:
        """Each tensor's gradient, the sum over the ranks of dL/dx, replaced by the preconditioned gradient. `phase`
        times this rank's own solves as "solve_backward.own"."""
        with (phase or _untimed)("solve_backward.own"):
            for tensor, owner in self.shares:
                if owner == self.rank:
                    tensor.param.grad.copy_(tensor.precondition_gradient(tensor.param.grad))
        works = [dist.broadcast(t.param.grad, owner, async_op=True) for t, owner in self.shares]
        for work in works:
            work.wait()

    def close(self) -> None:
        """The tensors solve in their autograd pass again."""
        for tensor, _ in self.shares:
            tensor.defer_gradient = False


class SilentProgress:
    """The progress report of a rank other than 0: rank 0 reports for all."""

    def record(self, row: dict) -> None:
        pass

    def step(self, iteration: int, done: float, evaluated: bool = False) -> None:
        pass

    def print_line(self, iteration: int, done: float) -> None:
        pass

    def finish(self, iteration: int) -> None:
        pass

    def close(self) -> None:
        pass


@dataclass
class Parallel:
    """This process's place in a data-parallel fit: its rank among `world`, its device, the host-side group that
    carries rank 0's decisions, the clock it reads, and who is told of its gradient all-reduce (`on_reducer`)."""

    rank: int
    world: int
    device: torch.device
    control: object  # a gloo process group (the default group where that is gloo)
    clock: Callable[[], float] = time.perf_counter
    on_reducer: Callable[[GradientReducer], None] | None = None  # told of the gradient all-reduce (a benchmark's hook)
    _reducer: GradientReducer | None = field(default=None, repr=False)

    @property
    def lead(self) -> bool:
        """Rank 0: decides, evaluates, logs and writes."""
        return self.rank == 0

    def shared(self, *values: float) -> tuple[float, ...]:
        """Rank 0's `values`, on every rank (a broadcast on the host; the others' values are ignored)."""
        packet = torch.tensor(values, dtype=torch.float64)
        dist.broadcast(packet, 0, group=self.control)
        return tuple(packet.tolist())

    def decide(self, stop: bool, done: float, digest: int, iteration: int) -> tuple[bool, float]:
        """Rank 0's time-budget `stop` and run fraction `done` before an iteration, on every rank; checks that this
        rank's picks of the iteration have rank 0's `digest` (a rank drawing otherwise would compute another)."""
        lead_stop, lead_done, lead_digest = self.shared(float(stop), done, float(digest))
        if int(lead_digest) != digest:
            raise RuntimeError(f"data-parallel fit: rank {self.rank} drew other views than rank 0 at iteration "
                               f"{iteration} (picks digest {digest} against {int(lead_digest)})")
        return bool(lead_stop), lead_done

    def sum_terms(self, terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Loss terms summed over the ranks (each rank's are its part of the iteration's), in one all-reduce."""
        if not terms:
            return terms
        keys = sorted(terms)
        stacked = torch.stack([torch.as_tensor(terms[k], dtype=torch.float32, device=self.device).reshape(()) for k in keys])
        dist.all_reduce(stacked)
        return dict(zip(keys, stacked.unbind()))

    def sum_count(self, count: torch.Tensor) -> "SummedCount":
        """A count (a device scalar) summed over the ranks, on the device (no wait for the host): launched now, and
        waited for where its value is used (SummedCount), so that the work queued between runs while the collective
        waits for the slowest rank."""
        total = count.to(torch.float32).reshape(1).clone()
        return SummedCount(total, dist.all_reduce(total, async_op=True))

    def reduce_gradients(self, model: torch.nn.Module) -> GradientReducer:
        """Install the gradient all-reduce on `model`'s parameters (once); `finish` it after each backward."""
        if self._reducer is None:
            self._reducer = GradientReducer(list(model.parameters()))
            if self.on_reducer is not None:
                self.on_reducer(self._reducer)
        return self._reducer

    def check_replicas(self, model: torch.nn.Module, when: str) -> None:
        """Raise unless every rank holds the same weights (a checksum of their bits, gathered on the host)."""
        digest = torch.tensor([replica_digest(model)], dtype=torch.int64)
        gathered = [torch.zeros_like(digest) for _ in range(self.world)]
        dist.all_gather(gathered, digest, group=self.control)
        values = [int(t) for t in gathered]
        if len(set(values)) != 1:
            raise RuntimeError(f"data-parallel fit: the ranks' weights differ {when} (checksums {values}); "
                               "the ranks no longer compute one fit")


def replica_digest(model: torch.nn.Module) -> int:
    """A checksum of the bits of `model`'s floating-point state (equal bits, equal checksum)."""
    total = torch.zeros((), dtype=torch.int64)
    widths = {1: torch.int8, 2: torch.int16, 4: torch.int32, 8: torch.int64}
    for t in model.state_dict().values():
        if t.is_floating_point() and t.numel():
            bits = t.detach().contiguous().view(widths[t.element_size()]).reshape(-1).to(torch.int64)
            weights = torch.arange(1, bits.numel() + 1, device=bits.device, dtype=torch.int64)
            total += (bits + bits * weights).sum().cpu()
    return int(total)


def lpips_shares(loss, total: int, parts: list[tuple[np.ndarray, torch.Tensor]],
                 sum_count: Callable[[torch.Tensor], object]) -> Callable[[np.ndarray], LossShare]:
    """The LPIPS term's random views and windows of an iteration's `total` views, drawn once (LossTerms.draw) as
    one evaluation of them all draws them, and a function from the places of some of them (among the iteration's
    views) to their LossShare. `parts`: (places, masks) of each evaluation to come, whose views with a mask among those drawn
    count towards the "mmlphuman" form's divisor, summed over the ranks by `sum_count` (Parallel.sum_count; in one
    process the count itself)."""
    pick, offsets = loss.draw(total) if loss.lpips_active else (None, None)
    seen = np.arange(total) if pick is None else pick  # the iteration's views that the LPIPS term sees
    count = None
    if loss.lpips_active and loss.cfg.lpips_form == "mmlphuman":  # its divisor: the LPIPS views with a mask
        mine = torch.zeros((), device=parts[0][1].device)
        for positions, masks in parts:
            sees = host_to_device(np.isin(positions, seen), masks.device)
            mine = mine + (masks.flatten(1).any(1) & sees).sum()
        count = sum_count(mine)
    elif loss.lpips_active:
        count = float(len(seen))

    def share_of(positions: np.ndarray) -> LossShare:
        rows = np.flatnonzero(np.isin(positions, seen))
        windows = None if offsets is None else offsets[np.searchsorted(seen, positions[rows])]
        return LossShare(len(positions) / total, None if pick is None else rows, windows, count)

    return share_of


def shard_loss(model, batch: TrainingBatch, loss, raster, background: torch.Tensor, phase, parallel: Parallel
               ) -> dict[str, torch.Tensor]:
    """This rank's part of Eq. 15 for its part of an iteration's views (`batch.share`), whose sum over the ranks is
    pig.avatar.training.iteration_loss of the whole iteration's views (with `fit.batched_render` or without: either
    draws the LPIPS term's views and windows once for the iteration, `lpips_shares`).

    The rank's timesteps that have as many views of one size render in one rasterizer call; the loss takes each
    image size's views in one evaluation."""
    with phase("model"):
        g = model(batch.timestep_tensor(background.device), batch.lod)
    groups: dict[tuple[int, int, int], list[tuple[int, object]]] = {}
    for k, step_batches in enumerate(batch.views):
        for vb in step_batches:
            groups.setdefault((vb.width, vb.height, len(vb.cameras)), []).append((k, vb))
    place, total = batch.places()
    by_size: dict[tuple[int, int], list] = {}
    with phase("render"):
        for (width, height, _), members in groups.items():
            ks = host_to_device(np.array([k for k, _ in members]), g.means.device)
            out = render_timesteps(g.means[ks], g.quats[ks], g.scales[ks], g.opacities[ks], g.sh[ks],
                                   torch.stack([vb.viewmats for _, vb in members]), torch.stack([vb.Ks for _, vb in members]),
                                   width, height, background, backend=raster.backend, max_pairs=raster.max_pairs)
            for (k, vb), color in zip(members, out.color):
                by_size.setdefault((width, height), []).append(([place[(k, c)] for c in vb.cameras], color, vb))
    with phase("loss"):
        evaluations = []  # one an image size: (places, render, images, masks, bands, height)
        for (width, height), parts in sorted(by_size.items()):
            positions = np.concatenate([np.asarray(p) for p, _, _ in parts])
            render = torch.cat([color for _, color, _ in parts])
            images, masks = (torch.cat([getattr(vb, name) for _, _, vb in parts]) for name in ("images", "masks"))
            bands = None if parts[0][2].bands is None else torch.cat([vb.bands for _, _, vb in parts])
            evaluations.append((positions, render, images, masks, bands, height))
        share_of = lpips_shares(loss, total, [(e[0], e[3]) for e in evaluations], parallel.sum_count)
        terms: dict[str, torch.Tensor] = {}
        for positions, render, images, masks, bands, height in evaluations:
            for key, value in loss(render, images, masks, height, bands, share_of(positions)).items():
                terms[key] = terms.get(key, 0) + value
    return terms
