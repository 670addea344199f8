"""Parity of the metric networks in float16 / bfloat16 (evaluate.lpips_precision, fid_precision) with float32 (CPU).

Ground truth: frames of a synthetic capture (pig.data.synthetic, `--views` views at the largest `--sizes` size,
masked to black as the protocol masks them; the smaller sizes are area-resized copies). Renders: each truth
perturbed as a fitted avatar's render differs from it (`perturbed`: blur, a two-pixel shift, a colour gain and
noise; PSNR printed). Per size and setting: the largest |LPIPS - LPIPS_float32| over the images, against issue 39's
1e-3, and the largest relative difference, with random-weight LPIPS-VGG (`LPIPS(weights="random")`, the fit's
stand-in path). FID: truths against renders (at each of `--fid-strengths`) over `--fid-views` smaller views, through
benchmarks/eval_scale.py's stand-in Inception (random convolutions of Inception-v3's cost), its relative change
against 0.5 %. Random weights are a stand-in: trained
networks' activations span other ranges, so the GPU parity test (tests/gpu/test_evaluate_precision_gpu.py) decides.

float16 convolutions on a CPU without float16 arithmetic are slow: `--float16-max-pixels` runs them under autocast
only up to that size, and every size also gets `float16 emulated`, float32 convolutions of float16-rounded inputs
and weights whose outputs are rounded to float16, as a GPU's float16 convolutions accumulate in float32.

    python benchmarks/metric_precision.py --workdir /tmp/precision
    python benchmarks/metric_precision.py --workdir /tmp/precision --sizes 320x288 --views 2 --fid-views 12
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_scale import InceptionStandIn  # noqa: E402

from pig.metrics.fid import InceptionFeatures, frechet_distance  # noqa: E402
from pig.metrics.lpips import LPIPS  # noqa: E402

LPIPS_BOUND, FID_BOUND = 1e-3, 5e-3  # issue 39: absolute per image; relative


def synthetic_views(workdir: Path, views: int, width: int, height: int,
                    workers: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(truths (N, H, W, 3) uint8 masked to black, masks (N, H, W) bool) of `views` views of a synthetic capture
    (two frames, views / 2 cameras, rounded up), generated once per size under `workdir`."""
    from pig.data.synthetic import SyntheticConfig, generate_capture

    cameras = max(1, -(-views // 2))
    raw = workdir / f"raw_{cameras}x2_{width}x{height}"
    if not (raw / "calibration.json").is_file():
        generate_capture(raw, SyntheticConfig(cameras=cameras, frames=2, width=width, height=height, workers=workers),
                         overwrite=True, progress=False)
    truths, masks = [], []
    for path in sorted((raw / "images").glob("cam*/*.jpg"))[:views]:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1]
        mask = cv2.imread(str(raw / "masks" / path.parent.name / path.name), cv2.IMREAD_GRAYSCALE) > 127
        truths.append(image * mask[..., None])
        masks.append(mask)
    return np.stack(truths), np.stack(masks)


def perturbed(truths: np.ndarray, seed: int = 0, strength: float = 1.0) -> np.ndarray:
    """Render-like copies of `truths` (N, H, W, 3) uint8: Gaussian blur, a two-pixel shift, a colour gain, noise."""
    rng = np.random.default_rng(seed)
    out = []
    for image in truths.astype(np.float32) / 255:
        image = cv2.GaussianBlur(image, (0, 0), 1.5 * strength)
        image = np.roll(image, 2, axis=1) * (1 - 0.05 * strength * rng.random(3, dtype=np.float32))
        image = image + rng.normal(0, 0.02 * strength, image.shape).astype(np.float32)
        out.append(np.clip(np.round(image * 255), 0, 255).astype(np.uint8))
    return np.stack(out)


def as_tensor(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255


def resized(images: np.ndarray, width: int, height: int) -> np.ndarray:
    return np.stack([cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA) for image in images])


@contextlib.contextmanager
def float16_emulated(modules: list[torch.nn.Module]):
    """Every Conv2d of `modules` computes in float32 on float16-rounded inputs and weights, its output rounded to
    float16 (ReLU and max-pooling are exact on such values): a GPU's float16 convolution, accumulating in float32."""
    def rounded(t: torch.Tensor) -> torch.Tensor:
        return t.to(torch.float16).to(t.dtype)

    convs = [m for module in modules for m in module.modules() if isinstance(m, torch.nn.Conv2d)]
    saved = [(conv.weight.data, None if conv.bias is None else conv.bias.data) for conv in convs]
    handles = []
    for conv in convs:
        conv.weight.data = rounded(conv.weight.data)
        if conv.bias is not None:
            conv.bias.data = rounded(conv.bias.data)
        handles.append(conv.register_forward_pre_hook(lambda _, args: (rounded(args[0]),)))
        handles.append(conv.register_forward_hook(lambda _, __, output: rounded(output)))
    try:
        yield
    finally:
        for handle in handles:
            handle.remove()
        for conv, (weight, bias) in zip(convs, saved):
            conv.weight.data = weight
            if bias is not None:
                conv.bias.data = bias


SETTINGS = [("float32", True), ("bfloat16", False), ("bfloat16", True), ("float16", False), ("float16", True),
            ("float16 emulated", False)]


def lpips_values(truths: torch.Tensor, renders: torch.Tensor, precision: str, channels_last: bool,
                 batch: int) -> np.ndarray:
    emulated = precision == "float16 emulated"
    net = LPIPS("vgg", weights="random", seed=0, precision="float32" if emulated else precision,
                channels_last=channels_last)
    values = []
    with torch.no_grad(), (float16_emulated([net.features]) if emulated else contextlib.nullcontext()):
        for start in range(0, len(truths), batch):
            values.append(net(renders[start:start + batch], truths[start:start + batch]))
    return torch.cat(values).double().numpy()


def fid_value(truths: torch.Tensor, renders: torch.Tensor, inception_path: Path, precision: str,
              channels_last: bool, batch: int) -> float:
    if precision == "float16 emulated":
        # The eager stand-in (hooks need it), called as InceptionFeatures calls the TorchScript file.
        torch.manual_seed(0)
        net = InceptionStandIn()
        from pig.metrics.fid import resize_for_inception

        def features(images):
            with float16_emulated([net]):
                return net(resize_for_inception(images).clamp(0, 1) * 255, return_features=True)
    else:
        features = InceptionFeatures(inception_path, precision=precision, channels_last=channels_last)
    stats = []
    with torch.no_grad():
        for images in (renders, truths):
            rows = torch.cat([features(images[s:s + batch]) for s in range(0, len(images), batch)]).double().numpy()
            stats.append((rows.mean(0), np.cov(rows, rowvar=False)))
    return frechet_distance(*stats[0], *stats[1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--sizes", nargs="+", default=["1330x1150", "665x575", "320x288"], help="W x H, largest first")
    parser.add_argument("--views", type=int, default=4, help="image pairs per size")
    parser.add_argument("--fid-views", type=int, default=48, help="images per FID set")
    parser.add_argument("--fid-size", default="320x288")
    parser.add_argument("--fid-strengths", type=float, nargs="+", default=[1.0, 4.0],
                        help="perturbation strengths of the FID's renders (4: a far blurrier, noisier set)")
    parser.add_argument("--float16-max-pixels", type=int, default=700 * 600,
                        help="float16 under autocast only up to this many pixels a view (slow on most CPUs)")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.workdir.mkdir(parents=True, exist_ok=True)
    sizes = [tuple(int(v) for v in size.split("x")) for size in args.sizes]
    truths, masks = synthetic_views(args.workdir, args.views, *sizes[0])
    renders = perturbed(truths)
    inception_path = args.workdir / "inception_standin.pt"
    torch.manual_seed(0)
    torch.jit.script(InceptionStandIn()).save(str(inception_path))  # the weights the emulated row rebuilds from seed 0

    rows = []
    print(f"torch {torch.__version__}, {args.threads} threads; LPIPS-VGG random weights (seed 0); {args.views} views "
          f"of a synthetic capture masked to black, renders perturbed")
    print(f"{'setting':<26} {'size':>10} {'images':>6} {'PSNR dB':>8} {'LPIPS f32':>10} {'max |dLPIPS|':>13} "
          f"{'max rel':>9} {'s/pass':>7}")
    for width, height in sizes:
        t, r = (as_tensor(resized(a, width, height)) for a in (truths, renders))
        psnr = float(np.mean([10 * np.log10(1 / ((x - y) ** 2).mean().item()) for x, y in zip(r, t)]))
        reference = None
        for precision, channels_last in [("float32", False), *SETTINGS]:
            if precision == "float16" and width * height > args.float16_max_pixels:
                continue
            start = time.perf_counter()
            values = lpips_values(t, r, precision, channels_last, args.batch)
            seconds = (time.perf_counter() - start) / (2 * len(t))
            if reference is None:
                reference = values
            setting = precision + (" channels-last" if channels_last else "")
            worst = float(np.abs(values - reference).max())
            relative = float((np.abs(values - reference) / reference).max())
            rows.append({"setting": setting, "size": f"{width}x{height}", "images": len(t), "psnr": psnr,
                         "lpips_float32": float(reference.mean()), "max_abs_diff": worst,
                         "max_relative_diff": relative, "s_per_pass": seconds})
            print(f"{setting:<26} {width:>5}x{height:<4} {len(t):>6} {psnr:>8.2f} {reference.mean():>10.4f} "
                  f"{worst:>13.2e} {relative:>9.2e} {seconds:>7.2f}", flush=True)

    fid_w, fid_h = (int(v) for v in args.fid_size.split("x"))
    fid_truths, _ = synthetic_views(args.workdir, args.fid_views, fid_w, fid_h)
    t = as_tensor(fid_truths)
    print(f"\nFID, stand-in Inception, {len(t)} renders against {len(t)} truths at {fid_w}x{fid_h} (resized to 299); "
          f"float16 emulated only (autocast float16 is slow here)")
    print(f"{'setting':<26} {'strength':>8} {'FID':>12} {'relative change':>16}")
    for strength in args.fid_strengths:
        r = as_tensor(perturbed(fid_truths, seed=1, strength=strength))
        reference = None
        for precision, channels_last in [("float32", False), *SETTINGS]:
            if precision == "float16":
                continue
            fid = fid_value(t, r, inception_path, precision, channels_last, 8)
            reference = fid if reference is None else reference
            setting = precision + (" channels-last" if channels_last else "")
            change = abs(fid - reference) / reference
            rows.append({"setting": setting, "fid_size": args.fid_size, "fid_images": len(t), "strength": strength,
                         "fid": fid, "fid_relative_change": change})
            print(f"{setting:<26} {strength:>8g} {fid:>12.6g} {change:>16.2e}", flush=True)
    print(f"\nbounds: LPIPS {LPIPS_BOUND:g} absolute per image, FID {FID_BOUND:.1%} relative")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
