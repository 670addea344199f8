"""The synthetic capture's render workers: what runs in them, and the pool that starts them.

Apart from pig.data.synthetic.capture so that a worker imports no torch (numpy, OpenCV, trimesh and Embree only):
the workers start together and their imports are most of their start-up (benchmarks/NOTES.md, "Synthetic capture
generator: workers start together").
"""
from __future__ import annotations

import multiprocessing
import multiprocessing.pool
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .render import render_frame

_WORKER: dict = {}


def init_worker(appearance, cameras, body, garment, root, supersample, quality) -> None:
    _WORKER.update(appearance=appearance, cameras=cameras, body=body, garment=garment, root=Path(root),
                   supersample=supersample, quality=quality, ready=time.perf_counter())
    cv2.setNumThreads(1)


def _receive_inputs(inputs: multiprocessing.Queue) -> None:
    init_worker(*inputs.get())


def render_and_write(task: tuple[list[int], list[int]]) -> dict:
    """Render and write the views of some frames seen by some cameras; returns the task's record for a
    RenderTimeline (its views, its worker, when it ran and its seconds per part)."""
    start = time.perf_counter()
    frames, camera_ids = task
    w = _WORKER
    cameras = [w["cameras"][c] for c in camera_ids]
    parts: dict[str, float] = {}
    for frame in frames:
        for camera, rgb, mask in render_frame(w["appearance"], w["body"][frame], w["garment"][frame], cameras,
                                              w["supersample"], parts):
            written = time.perf_counter()
            name = f"{frame:08d}.jpg"
            image = cv2.cvtColor((rgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
            _imwrite(w["root"] / "images" / camera.name / name, image, w["quality"])
            _imwrite(w["root"] / "masks" / camera.name / name, mask.astype(np.uint8) * 255, w["quality"])
            parts["write"] = parts.get("write", 0.0) + time.perf_counter() - written
    return {"views": len(frames) * len(cameras), "frames": frames, "cameras": camera_ids, "pid": os.getpid(),
            "ready": w["ready"], "start": start, "end": time.perf_counter(), "parts": parts}


@dataclass
class RenderTimeline:
    """Where the render workers' time went: one record per task (render_and_write), in the order they ended.

    Times are time.perf_counter() values, one clock for every process of a Linux host; `started` is when the parent
    began starting the workers, `ended` when the last task came back."""

    workers: int = 0
    started: float = 0.0
    ended: float = 0.0
    tasks: list[dict] = field(default_factory=list)


def _imwrite(path: Path, image: np.ndarray, quality: int) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, quality]):
        raise OSError(f"could not write {path}")


# Set for the render workers as they start: one BLAS (and OpenMP) thread each. OpenBLAS otherwise starts a thread per
# core of the host in every worker, and its idle threads spin: on a 64-core host 16 workers spent 57 CPU-minutes
# on 240 views, ~14 CPU-s a view against ~3 in one single-threaded process (benchmarks/NOTES.md, "Synthetic capture
# generator"). The workers already split the views across the cores.
WORKER_THREAD_LIMITS = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def worker_pool(workers: int, init: tuple) -> multiprocessing.pool.Pool:
    """`workers` spawned render processes, initialised with `init_worker(*init)` and started with
    WORKER_THREAD_LIMITS in their environment; this process's is left as it was.

    Spawn, not fork: the parent holds torch's thread pools, which do not survive a fork. The workers start together:
    `init` (the meshes: ~5 MB for 10 frames) reaches them through a queue, since spawn writes a worker's start arguments
    into a pipe that holds 64 KiB and waits for the worker to read them, which it does only after its imports, so
    workers with `init` as their arguments started one after another (benchmarks/NOTES.md). Nor do they import this
    process's main module as spawn would (a script such as benchmarks/fit_gpu.py imports torch's compiler and the
    fitting code): they run this module's functions only."""
    context = multiprocessing.get_context("spawn")
    inputs = context.Queue()
    inputs.cancel_join_thread()  # workers stopped before reading their copy must not keep this process waiting
    main = sys.modules["__main__"]
    saved = {name: os.environ.get(name) for name in WORKER_THREAD_LIMITS}
    os.environ.update(WORKER_THREAD_LIMITS)
    spec, path = main.__spec__, main.__dict__.pop("__file__", None)  # what spawn reads to import the main module
    main.__spec__ = None
    try:
        pool = context.Pool(workers, initializer=_receive_inputs, initargs=(inputs,))  # the workers start here
    finally:
        main.__spec__ = spec
        if path is not None:
            main.__file__ = path
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name)
            else:
                os.environ[name] = value
    for _ in range(workers):
        inputs.put(init)
    return pool
