"""Render and evaluate at the THuman4 protocol's scale: wall time, views/s, peak host/GPU memory, bytes per stage.

Builds a capture of THuman4's dimensions (24 cameras, 2000 training + 500 novel-pose frames, 1330 x 1150):
`--generated-frames` frames are generated and preprocessed, the others repeat their images by hard links
(as benchmarks/data_scale.py does) under SMPL-X poses that never repeat (seeded noise on the body joints), so
every frame is its own pose and nearest-timestep lookup. The split is THuman4's: cam23 held out on the training
frames (novel view), all 24 cameras on the last 500 (novel pose); `--fraction` scales both frame counts. An
avatar with one timestep per training frame is fitted for `--iterations` iterations, then the render stage
runs per split and the evaluate stage per split and LOD, each as its own process with the workflow's command
line, so old and new code (`--code`) run the same way. LPIPS-VGG and FID use stand-in random weights written
to the work folder's torch hub cache (real weights cost the same time).

    python benchmarks/eval_scale.py --workdir /tmp/evscale                     # CUDA: paper preset, whole protocol
    python benchmarks/eval_scale.py --workdir /tmp/evscale --device cpu --preset cpu-demo --fraction 0.004 \\
        --width 333 --height 288 --iterations 20 --code /path/to/other/checkout
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from data_scale import build_capture, tile_capture  # noqa: E402

from pig.body.params import SmplxParams  # noqa: E402
from pig.config import load_preset  # noqa: E402

CAMERAS, TRAIN_FRAMES, POSE_FRAMES = 24, 2000, 500  # config/datasets/thuman4.yaml
HELD_OUT = "cam23"


def protocol_capture(workdir: Path, fraction: float, width: int, height: int, generated: int, workers: int) -> Path:
    """The THuman4-sized capture (see the module docstring); built once per size."""
    train, pose = max(2, round(TRAIN_FRAMES * fraction)), max(1, round(POSE_FRAMES * fraction))
    target = workdir / f"capture_{train}+{pose}_{width}x{height}"
    if (target / "report.json").is_file():
        return target
    source, _ = build_capture(workdir, CAMERAS, generated, width, height, workers)
    tile_capture(source, target, train + pose)
    params, ids = SmplxParams.load(target / "smplx.npz")
    rng = np.random.default_rng(0)
    pose_noise = np.zeros_like(params.full_pose)
    pose_noise[:, 1:22] = rng.normal(0.0, 0.05, (len(ids), 21, 3))  # body joints: no two frames share a pose
    SmplxParams(params.full_pose + pose_noise, params.betas, params.expression, params.transl).save(
        target / "smplx.npz", frame_ids=ids)
    cameras = sorted(json.loads((target / "cameras.json").read_text()))
    if HELD_OUT not in cameras:
        raise SystemExit(f"{target}: expected cameras cam00..cam23, found {cameras}")
    split = {"train": {"cameras": [c for c in cameras if c != HELD_OUT], "frames": list(range(train))},
             "novel_view": {"cameras": [HELD_OUT], "frames": list(range(train))},
             "novel_pose": {"cameras": cameras, "frames": list(range(train, train + pose))}}
    (target / "split.json").write_text(json.dumps(split))
    return target


def stand_in_weights(torch_home: Path) -> None:
    """Random LPIPS-VGG (VGG-16 features by torchvision's keys + lpips linear layers) and a TorchScript
    Inception stand-in in `torch_home`/hub/checkpoints under the published names."""
    from pig.metrics.lpips import backbone_features
    from pig.metrics.weights import INCEPTION_FILE, LPIPS_LINEAR_FILES, TORCHVISION_FILES

    folder = torch_home / "hub" / "checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    if not (folder / TORCHVISION_FILES["vgg"]).is_file():
        features = backbone_features("vgg")
        for layer in features:
            if isinstance(layer, torch.nn.Conv2d):
                torch.nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
        torch.save({f"features.{k}": v for k, v in features.state_dict().items()}, folder / TORCHVISION_FILES["vgg"])
        widths = [64, 128, 256, 512, 512]
        torch.save({f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) * 2 / c for k, c in enumerate(widths)},
                   folder / LPIPS_LINEAR_FILES["vgg"])
    if not (folder / INCEPTION_FILE).is_file():
        torch.jit.script(InceptionStandIn()).save(str(folder / INCEPTION_FILE))


class InceptionStandIn(torch.nn.Module):
    """Random convolutions of Inception-v3's cost (7.1 GFLOP at 299 x 299 against its 5.7) to 2048 pooled
    features, called as the StyleGAN/clean-fid file is (no torchvision on the machines)."""

    def __init__(self):
        super().__init__()
        widths, layers = [3, 32, 64, 192, 384, 768], []
        for k, (c_in, c_out) in enumerate(zip(widths, widths[1:])):
            layers += [torch.nn.Conv2d(c_in, c_out, 3, stride=1 if k == 1 else 2, padding=1), torch.nn.ReLU()]
        self.net = torch.nn.Sequential(*layers, torch.nn.Conv2d(768, 2048, 1), torch.nn.AdaptiveAvgPool2d(1))

    def forward(self, x: torch.Tensor, return_features: bool = False) -> torch.Tensor:
        return self.net(x / 127.5 - 1).flatten(1)


def write_preset(workdir: Path, preset: str, iterations: int, device: str, evaluate: dict) -> Path:
    data = load_preset(preset)
    data.pop("_path", None)
    data.setdefault("fit", {}).update(iterations=iterations, eval_every=10**9, checkpoint_minutes=10**6,
                                      weight_lpips=0.0)  # the fit only makes renders like a real fit's
    data.setdefault("evaluate", {}).update(lpips_net="vgg", device=device, **evaluate)
    path = workdir / "eval_scale_preset.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def run_stage(module: str, args: list[str], env: dict, report: Path) -> dict:
    """Run one stage in a fresh process as the workflow does; its wall time, peak RSS and peak GPU memory."""
    report.unlink(missing_ok=True)
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, __file__, "--stage", module, str(report), *args], env=env)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{module} {' '.join(args)} failed (exit {os.waitstatus_to_exitcode(status)})")
    gpu = json.loads(report.read_text())["peak_gpu_mib"] if report.is_file() else float("nan")
    return {"wall_s": wall, "peak_rss_mib": usage.ru_maxrss / 1024, "peak_gpu_mib": gpu}


def stage_child(module: str, report: str, args: list[str]) -> int:
    from pig._cli import run_cli

    code = run_cli(importlib.import_module(module).main, args)
    peak = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else float("nan")
    Path(report).write_text(json.dumps({"peak_gpu_mib": peak}))
    return code


def codec_table(split_dir: Path, count: int) -> list[dict]:
    """Bytes per view, encode and decode ms per view (one thread) of each lossless codec on `count` rendered views
    of the finest LOD, read back from the render stage's storage."""
    from pig.data.images import decode_image
    from pig.data.render_store import CODECS, RenderReader, encode_image

    level = max(int(p.name[3:]) for p in split_dir.glob("lod*"))
    reader = RenderReader(split_dir / f"lod{level}")
    manifest = json.loads((split_dir / "manifest.json").read_text())
    views = [(cam, frame) for frame in manifest["frames"] for cam in manifest["cameras"]][:count]
    images = [reader.image_u8(cam, frame) for cam, frame in views]
    rows = []
    print(f"\n{len(images)} views of {split_dir.name} lod{level}, {images[0].shape[1]} x {images[0].shape[0]}, one thread")
    print(f"{'codec':<6} {'KB/view':>8} {'encode ms':>10} {'decode ms':>10}")
    for codec in CODECS:
        start = time.perf_counter()
        streams = [encode_image(image, codec) for image in images]
        encode = time.perf_counter() - start
        start = time.perf_counter()
        decoded = [decode_image(stream, codec) for stream in streams]
        decode = time.perf_counter() - start
        if not all(np.array_equal(d[..., ::-1], image) for d, image in zip(decoded, images)):
            raise SystemExit(f"{codec}: a view did not decode to the same pixels")
        row = {"codec": codec, "bytes_per_view": sum(s.size for s in streams) / len(images),
               "encode_ms": 1000 * encode / len(images), "decode_ms": 1000 * decode / len(images)}
        rows.append(row)
        print(f"{codec:<6} {row['bytes_per_view'] / 1024:>8.1f} {row['encode_ms']:>10.1f} {row['decode_ms']:>10.1f}")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--fraction", type=float, default=1.0, help="share of THuman4's 2000 + 500 frames")
    parser.add_argument("--width", type=int, default=1330)
    parser.add_argument("--height", type=int, default=1150)
    parser.add_argument("--generated-frames", type=int, default=4, help="frames generated; the rest hard links")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    parser.add_argument("--iterations", type=int, default=300, help="iterations of the brief fit")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="generate/preprocess processes")
    parser.add_argument("--code", type=Path, default=None,
                        help="checkout whose stages run (PYTHONPATH); default: the one this script imports")
    parser.add_argument("--splits", nargs="+", default=["novel_view", "novel_pose"])
    parser.add_argument("--tag", default="", help="name of this code's results folder (default: new/other)")
    parser.add_argument("--codec", choices=["png", "webp"], default=None, help="evaluate.render_codec (preset's)")
    parser.add_argument("--encode-workers", type=int, default=None, help="evaluate.encode_workers (preset's)")
    parser.add_argument("--batch-size", type=int, default=None, help="evaluate.batch_size (preset's)")
    parser.add_argument("--codec-sample", type=int, default=0,
                        help="also time every codec on this many rendered novel-pose views (one thread)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    capture = protocol_capture(args.workdir, args.fraction, args.width, args.height, args.generated_frames,
                               args.workers)
    torch_home = args.workdir / "torch_home"
    stand_in_weights(torch_home)
    env = {**os.environ, "TORCH_HOME": str(torch_home), "PYTHONPATH": os.pathsep.join(
        [str(args.code.resolve()) if args.code else str(Path(__file__).resolve().parents[1]),
         *filter(None, [os.environ.get("PYTHONPATH")])])}
    evaluate = {key: value for key, value in (("render_codec", args.codec), ("encode_workers", args.encode_workers),
                                              ("batch_size", args.batch_size)) if value is not None}
    preset = write_preset(args.workdir, args.preset, args.iterations, args.device, evaluate)
    variant = args.workdir / f"{capture.name}_{args.preset}_{args.iterations}" / "pig"
    if not (variant / "avatar.pt").is_file():
        fitted = run_stage("pig.stages.fit", ["--capture", str(capture), "--output", str(variant), "--preset",
                                              str(preset), "--device", args.device], env, args.workdir / "peak.json")
        print(f"fit ({args.iterations} iterations): {fitted['wall_s']:.1f} s", flush=True)
    results = variant.parent / (args.tag or ("other" if args.code else "new"))
    shutil.rmtree(results, ignore_errors=True)
    split = json.loads((capture / "split.json").read_text())
    rows = []
    for name in args.splits:
        views = len(split[name]["cameras"]) * len(split[name]["frames"])
        renders = results / "renders" / name
        row = run_stage("pig.stages.render", ["--checkpoint", str(variant / "avatar.pt"), "--capture", str(capture),
                                              "--split", name, "--output", str(renders), "--preset", str(preset)],
                        env, args.workdir / "peak.json")
        levels = sorted(int(p.name[3:]) for p in renders.glob("lod*"))
        rows.append({"stage": "render", "split": name, "views": views * len(levels), **row,
                     "bytes": folder_bytes(renders)})
        for level in levels:
            row = run_stage("pig.stages.evaluate", ["--capture", str(capture), "--renders", str(renders), "--split",
                                                    name, "--lod", str(level), "--output", str(results / "metrics"),
                                                    "--preset", str(preset)], env, args.workdir / "peak.json")
            summary = json.loads((results / "metrics" / f"{name}_lod{level}.json").read_text())
            rows.append({"stage": f"evaluate lod{level}", "split": name, "views": views, **row,
                         "bytes": sum((results / "metrics" / f"{name}_lod{level}{ext}").stat().st_size
                                      for ext in (".csv", ".json")),
                         "psnr": summary["psnr"], "lpips": summary["lpips"], "fid": summary["fid"]})
    print(f"\ncapture {capture.name}: {args.width} x {args.height}, code {env['PYTHONPATH'].split(os.pathsep)[0]}, "
          f"device {args.device}, preset {args.preset}")
    print(f"{'stage':<14} {'split':<11} {'views':>7} {'wall s':>8} {'views/s':>8} {'RSS MiB':>8} {'GPU MiB':>8} "
          f"{'bytes':>12} {'B/view':>8}")
    for row in rows:
        print(f"{row['stage']:<14} {row['split']:<11} {row['views']:>7} {row['wall_s']:>8.1f} "
              f"{row['views'] / row['wall_s']:>8.1f} {row['peak_rss_mib']:>8.0f} {row['peak_gpu_mib']:>8.0f} "
              f"{row['bytes']:>12} {row['bytes'] / row['views']:>8.0f}")
    total = {key: sum(row[key] for row in rows) for key in ("wall_s", "bytes")}
    print(f"{'total':<14} {'':<11} {'':>7} {total['wall_s']:>8.1f} {'':>8} {'':>8} {'':>8} {total['bytes']:>12}")
    codecs = codec_table(results / "renders" / "novel_pose", args.codec_sample) if args.codec_sample else []
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "codecs": codecs, "args": {k: str(v) for k, v in vars(args).items()}}, indent=1))
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 3 and sys.argv[1] == "--stage":
        raise SystemExit(stage_child(sys.argv[2], sys.argv[3], sys.argv[4:]))
    raise SystemExit(main())
