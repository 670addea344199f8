"""Kernels of the compiled real-time frame (AvatarDriver._frame): library (extern) calls and generated kernels.

A device-free proxy for the frame graph's launch count: on CUDA each extern call is a cuBLAS launch inside the
graph that inductor cannot fuse with its neighbours. Runs on the CPU in under a minute, on a small unfitted avatar
of the `test` preset:

    python benchmarks/frame_kernels.py
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import torch
from torch._inductor.utils import run_and_get_code

from pig.avatar.driver import AvatarDriver
from pig.field.precondition import bake_preconditioning

sys.path.insert(0, str(Path(__file__).parent))
from render_fps import build_unfitted  # noqa: E402


def main() -> int:
    torch.manual_seed(0)
    model = build_unfitted("test", 2000, 10)
    bake_preconditioning(model)
    model.eval()
    driver = AvatarDriver(model, frame_graph=True)
    pose = model.pose_init[3] + 0.05
    lod = model.num_levels - 1
    driver.posed_frame(lod, pose)  # the per-avatar and per-LOD caches that the frame reads
    with torch.no_grad():
        _, codes = run_and_get_code(torch.compile(driver._frame, dynamic=False), lod, driver._pose(pose), None)
    code = "\n".join(codes)
    extern = re.findall(r"extern_kernels\.(\w+)\(", code)
    generated = set(re.findall(r"\b(?:cpp|triton)_\w*fused_\w+", code))
    print("| extern calls | of which bmm / mm | generated kernels |\n|---|---|---|")
    print(f"| {len(extern)} | {extern.count('bmm')} / {extern.count('mm')} | {len(generated)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
