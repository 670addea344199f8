"""LPIPS over the window of the frame where a render or the mask is not black (evaluate.lpips_window, LPIPS.window)
against LPIPS over the whole frame, on held-out views of a capture: the window's share of the frame, seconds per
batch of each path in interleaved rounds in one process (the device synchronised), their ratio, and the largest
relative difference of the two distances.

The renders are stand-ins made here from the truth: the masked ground truth blurred, spilling a few pixels past the
mask (a fit's renders spill about so), so the boxes are the subject's as evaluate would find them. Random network
weights (their cost is the real ones'). A THuman4-sized capture of the synthetic subject comes from
benchmarks/eval_scale.py (any capture folder will do):

    python -c "import sys; sys.path.insert(0, 'benchmarks'); from eval_scale import protocol_capture; \\
        from pathlib import Path; print(protocol_capture(Path('/tmp/share'), 0.004, 1330, 1150, 4, 2, 5))"
    python benchmarks/lpips_window.py --capture /tmp/share/capture_24x10_1330_up5 --views 2 --device cpu
    python benchmarks/lpips_window.py --capture ... --views 16 --device cuda --precision float16 --channels-last
"""
from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch

from pig.data.capture import Capture
from pig.metrics.lpips import LPIPS
from pig.stages.evaluate import nonzero_box, union_box


def stand_in_batch(capture: Capture, views: list[tuple[str, int]]) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """(renders, masked truths) as (B, 3, H, W) float32 in [0, 1], and the union of the masks' and renders' nonzero
    boxes, as the evaluate stage's loader finds them."""
    truths, renders, boxes = [], [], []
    for view in views:
        truth, mask = capture.image_u8(*view), capture.mask(*view)
        masked = truth * mask[..., None]
        spill = cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8))[..., None]
        render = (cv2.GaussianBlur(masked.astype(np.float32), (0, 0), 1.5) * spill).round().astype(np.uint8)
        truths.append(masked)
        renders.append(render)
        boxes += [nonzero_box(mask), nonzero_box(render)]
    as_floats = lambda images: torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float() / 255
    return as_floats(renders), as_floats(truths), union_box(boxes) or (0, 1, 0, 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", required=True, help="a preprocessed capture folder")
    parser.add_argument("--split", default="novel_pose")
    parser.add_argument("--views", type=int, default=2, help="views of one camera size in the batch")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--net", choices=["vgg", "alex"], default="vgg")
    parser.add_argument("--precision", choices=["float32", "float16", "bfloat16"], default="float32")
    parser.add_argument("--channels-last", action="store_true")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    capture = Capture.load(args.capture, cache_mb=0)
    first = capture.views(args.split)[0]
    size = lambda view: (capture.cameras[view[0]].width, capture.cameras[view[0]].height)
    views = [view for view in capture.views(args.split) if size(view) == size(first)][:args.views]
    x, y, box = stand_in_batch(capture, views)
    x, y = x.to(device), y.to(device)
    metric = LPIPS(args.net, weights="random", precision=args.precision, channels_last=args.channels_last).to(device)
    frame = tuple(x.shape[-2:])
    rows, cols = metric.window(box, *frame)
    share = (rows.stop - rows.start) * (cols.stop - cols.start) / (frame[0] * frame[1])
    paths = {
        "whole frame": lambda: metric.distance(x, metric.reference(y)),
        "window": lambda: metric.distance(x[..., rows, cols], metric.reference(y[..., rows, cols]), frame=frame),
    }
    seconds: dict[str, list[float]] = {name: [] for name in paths}
    values = {}
    with torch.no_grad():
        for name, path in paths.items():  # warm-up (cuDNN's choices, first allocations), not counted
            values[name] = path()
        for _ in range(args.rounds):
            for name, path in paths.items():
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                start = time.perf_counter()
                path()
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                seconds[name].append(time.perf_counter() - start)
    layout = ", channels-last" if args.channels_last else ""
    print(f"LPIPS-{args.net} ({args.precision}{layout}) on {args.device}: {len(views)} views of {args.split} at "
          f"{frame[1]} x {frame[0]}; window rows {rows.start}:{rows.stop}, columns {cols.start}:{cols.stop}, "
          f"{share:.1%} of the frame")
    print("| path | s per batch, by round | median |\n|---|---|---|")
    for name, times in seconds.items():
        print(f"| {name} | {', '.join(f'{t:.3f}' for t in times)} | {np.median(times):.3f} |")
    gap = ((values["window"] - values["whole frame"]).abs() / values["whole frame"]).max().item()
    print(f"window / whole frame: {np.median(seconds['window']) / np.median(seconds['whole frame']):.3f}; "
          f"largest |windowed - whole| / whole: {gap:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
