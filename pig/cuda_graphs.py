"""Capture of a device function as a CUDA graph, shared by the CG solver's iteration blocks (pig.field.knn_solve)
and the real-time frame (pig.avatar.driver).

A graph replays fixed kernels on fixed buffers: the function must read its inputs from tensors that the caller
refills in place, and it must not ask the host anything (no .item(), no host-to-device copies).
"""
from __future__ import annotations

from typing import Callable, TypeVar

import torch

T = TypeVar("T")
captures = 0  # graphs captured in this process: a fit's training seconds leave the steps that capture out


def capture(run: Callable[[], T], device: torch.device, warmups: int = 1) -> tuple[torch.cuda.CUDAGraph, T]:
    """(graph, outputs of the captured call) of `run()`. It is first called `warmups` times on a side stream, as
    capture requires: compilation and the allocator's first allocations must happen outside the graph."""
    global captures
    captures += 1
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        for _ in range(warmups):
            run()
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        outputs = run()
    return graph, outputs
