"""Counting the host synchronisations of a piece of torch code, on any device (the CPU included).

A GPU step that is bound by its host (Python, dispatch, launches) loses the device's queue at each synchronisation:
the host waits until the device has run everything queued, then the device idles while the host launches again.
`HostSyncs` records, while active, the calls that make a CUDA host wait for its device, by phase (a name the caller
keeps current) and by the Python line that made them; on the CPU nothing waits, but the calls are the same ones, so
a CPU run finds them:

- aten ops that read a tensor's value or a size computed from its values on the host (SYNC_OPS:
  `_local_scalar_dense` of .item(), float(), int(), bool(); `nonzero` and `torch.where(c)`; `masked_select`;
  `unique*`; `equal`; `bincount`; `histc` (counted whatever its bounds); `repeat_interleave` without `output_size`; `index` and
  `index_put_` with a boolean mask, i.e. x[mask]);
- the copies of device data to the host (Tensor.tolist, .numpy, .cpu, .to("cpu"));
- blocking copies of host data to the device (torch.tensor(..., device=...), .to(device) or copy_ of host data
  without non_blocking=True): a pageable copy waits for the stream (PyTorch's copy synchronises it); and copy_ of
  device data into a host tensor without non_blocking=True (with it, into pinned memory, the host goes on).

Tensors made from host data inside the window (torch.tensor, as_tensor, from_numpy, factories without a device) and
what is computed from them alone are host tensors: reading them waits for nothing on any device, and is not counted.
A host tensor moved with .to(device=...) is a device tensor from then on (on the CPU it may be the same object).
Not seen: ops inside compiled graphs and C++ internals below one aten op (a boolean index is seen as the index op),
and `torch._assert_async`, which does not synchronise (its failure is reported by the next synchronisation).
"""
from __future__ import annotations

import traceback
import weakref
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

SYNC_OPS = {"_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique", "_unique2", "unique_dim",
            "unique_consecutive", "unique_dim_consecutive", "equal", "is_nonzero", "bincount", "histc",
            "repeat_interleave"}
_MASK_INDEX_OPS = {"index", "index_put", "index_put_", "_index_put_impl_"}
_TO_HOST = {"tolist", "numpy", "cpu"}
_MAKERS = {"tensor", "as_tensor", "from_numpy", "asarray"}
_FACTORIES = {"zeros", "ones", "empty", "full", "arange", "linspace", "rand", "randn", "randint", "eye", "scalar_tensor"}
# Functions whose value checks read the device on the CPU only (torch's one_hot skips them on CUDA, where the scatter
# asserts on the device instead): their reads are recorded with the mark CPU_ONLY.
_CPU_ONLY_CHECKS = {"one_hot"}
CPU_ONLY = " (CPU only)"
_ROOT = str(Path(__file__).resolve().parent.parent)  # the repository: frames of pig/, benchmarks/, tests/
_SELF = str(Path(__file__).resolve())


@dataclass(frozen=True)
class Sync:
    """One kind of synchronisation: its phase, the op (an aten op's name, or Tensor.tolist and kin, or
    "blocking copy to device"), and the repository's Python lines that made it, innermost first."""

    phase: str
    op: str
    stack: tuple[str, ...]

    @property
    def site(self) -> str:
        return self.stack[0] if self.stack else "?"


def repository_stack(depth: int = 4) -> tuple[str, ...]:
    """The `depth` innermost frames of the caller's stack that lie in this repository (not this module), innermost
    first, as "path:line (function)" with the path relative to the repository."""
    frames = []
    for frame in reversed(traceback.extract_stack()):
        path = str(Path(frame.filename).resolve()) if not frame.filename.startswith("<") else frame.filename
        if path == _SELF or not path.startswith(_ROOT) or "/site-packages/" in path:
            continue
        frames.append(f"{path[len(_ROOT) + 1:]}:{frame.lineno} ({frame.name})")
        if len(frames) == depth:
            break
    return tuple(frames)


class _HostTensors:
    """The host tensors made inside the window, by identity (weakly held: a dead tensor's id may be reused)."""

    def __init__(self):
        self._refs: dict[int, weakref.ref] = {}

    def add(self, t: torch.Tensor) -> None:
        self._refs[id(t)] = weakref.ref(t)

    def discard(self, t: torch.Tensor) -> None:
        self._refs.pop(id(t), None)

    def __contains__(self, t: torch.Tensor) -> bool:
        ref = self._refs.get(id(t))
        return ref is not None and ref() is t


def _tensors(*trees) -> list[torch.Tensor]:
    return [t for t in tree_leaves(list(trees)) if isinstance(t, torch.Tensor)]


class _FunctionLevel(TorchFunctionMode):
    def __init__(self, owner: "HostSyncs"):
        super().__init__()
        self.owner = owner

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        host = self.owner.host
        inputs = _tensors(args, kwargs)
        device_inputs = [t for t in inputs if t not in host]
        if name in _TO_HOST and args and isinstance(args[0], torch.Tensor) and args[0] not in host:
            self.owner.record(f"Tensor.{name}")
        elif name == "to" and args and isinstance(args[0], torch.Tensor):
            target = _target_device(args[1:], kwargs)
            non_blocking = kwargs.get("non_blocking") is True or any(a is True for a in args[1:])
            literal = any(isinstance(a, str) and a == "cpu" for a in (kwargs.get("device"), *args[1:]))  # named
            if target is not None and target.type == "cpu" and args[0] not in host and self.owner.device_is_host \
                    and not literal:
                pass  # a CPU fit moving its own data to its device, which is the host
            elif target is not None and target.type == "cpu" and args[0] not in host:
                self.owner.record("Tensor.to(cpu)")
            elif target is not None and args[0] in host and not non_blocking:
                self.owner.record("blocking copy to device")
        elif name == "copy_" and len(args) > 1 and isinstance(args[1], torch.Tensor) \
                and (args[0] in host) != (args[1] in host) \
                and not (kwargs.get("non_blocking") is True or any(a is True for a in args[2:])):
            self.owner.record("blocking copy to device" if args[1] in host else "blocking copy to host")
        elif name in _MAKERS and args and not isinstance(args[0], torch.Tensor) and kwargs.get("device") is not None:
            self.owner.record("blocking copy to device")
        checks = name in _CPU_ONLY_CHECKS
        self.owner._cpu_only += checks
        try:
            out = func(*args, **kwargs)
        finally:
            self.owner._cpu_only -= checks
        outputs = _tensors(out)
        if name == "to" and args and isinstance(args[0], torch.Tensor) and _target_device(args[1:], kwargs) is not None:
            for t in outputs:  # moved to a device (on the CPU perhaps the same object): a device tensor now
                host.discard(t)
        elif name in ("pin_memory",):
            for t in outputs:
                host.add(t)
        elif (name in _MAKERS or name in _FACTORIES) and kwargs.get("device") is None and not device_inputs:
            for t in outputs:
                host.add(t)
        elif inputs and not device_inputs:  # computed from host tensors alone
            for t in outputs:
                host.add(t)
        return out


def _target_device(args, kwargs) -> torch.device | None:
    target = kwargs.get("device")
    if target is None:
        for a in args:
            if isinstance(a, (str, torch.device)):
                target = a
                break
            if isinstance(a, torch.Tensor):
                target = a.device
                break
    return None if target is None else torch.device(target)


class _DispatchLevel(TorchDispatchMode):
    def __init__(self, owner: "HostSyncs"):
        super().__init__()
        self.owner = owner

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func._schema.name.split("::")[-1]
        inputs = _tensors(args, kwargs)
        on_device = any(t not in self.owner.host for t in inputs)
        if on_device and name in SYNC_OPS:
            if not (name == "repeat_interleave" and kwargs.get("output_size") is not None):
                self.owner.record(name)
        elif on_device and name in _MASK_INDEX_OPS:
            indices = args[1] if len(args) > 1 else kwargs.get("indices", [])
            if any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices or []):
                self.owner.record(f"{name} (boolean mask)")
        return func(*args, **kwargs)


class HostSyncs:
    """Records the host synchronisations (module docstring) of the code run while it is active (`with`), on this
    thread, by `phase()` (the caller's current phase name) and by the repository's lines that made them.

    `device_is_host`: the code's device is the CPU itself, so its .to(device) with a torch.device of the CPU are not
    copies (a CPU fit), while .to("cpu") with the name written out is (the host, named); .tolist()
    and kin of its tensors still are on a GPU and count."""

    def __init__(self, phase: Callable[[], str] = lambda: "", device_is_host: bool = True, depth: int = 4):
        self.phase, self.device_is_host, self.depth = phase, device_is_host, depth
        self.counts: Counter[Sync] = Counter()
        self.host = _HostTensors()
        self._modes = (_FunctionLevel(self), _DispatchLevel(self))
        self._cpu_only = 0  # inside a _CPU_ONLY_CHECKS function

    def record(self, op: str) -> None:
        self.counts[Sync(self.phase(), op + (CPU_ONLY if self._cpu_only else ""), repository_stack(self.depth))] += 1

    def __enter__(self) -> "HostSyncs":
        for mode in self._modes:
            mode.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        for mode in reversed(self._modes):
            mode.__exit__(*exc)

    def by_phase_op(self) -> Counter[tuple[str, str]]:
        """Counts by (phase, op)."""
        out: Counter[tuple[str, str]] = Counter()
        for sync, count in self.counts.items():
            out[(sync.phase, sync.op)] += count
        return out

    def table(self, title: str = "") -> str:
        """A markdown table: phase, op, count, the line that made it and its callers."""
        lines = [title] if title else []
        lines += ["| phase | op | count | line (callers) |", "|---|---|---|---|"]
        for sync, count in sorted(self.counts.items(), key=lambda kv: (kv[0].phase, kv[0].op, kv[0].stack)):
            callers = " < ".join(sync.stack[1:])
            lines.append(f"| {sync.phase or '-'} | {sync.op} | {count} | {sync.site}"
                         + (f" (< {callers})" if callers else "") + " |")
        if not self.counts:
            lines.append("| - | none | 0 | |")
        return "\n".join(lines)
