"""The evaluate pass on the GPU against a float32 run of the same views on the CPU.

Run on the GPU machine (skipped without CUDA). Two LODs of 12 views at 320 x 288, LPIPS-VGG and a stand-in
Inception with random weights (their cost and numerics, not their meaning): per image PSNR within 1e-3 dB, SSIM
within 1e-4, LPIPS within 1e-3, and each LOD's FID within 0.5 % (issue 39's bounds; cuDNN may pick TF32
convolutions, which these bounds allow).
"""
import copy

import numpy as np
import pytest
import torch

from pig.data.capture import Capture
from pig.data.images import read_png
from pig.data.render_store import ChunkEncoder, chunk_path, write_manifest
from pig.metrics.fid import InceptionFeatures
from pig.metrics.lpips import LPIPS
from pig.stages.evaluate import EvaluateConfig, evaluate_levels

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


def test_evaluate_on_the_gpu_matches_the_float32_cpu_run(tmp_path, rng):
    from test_metrics import _TinyInception, _tiny_capture

    frames = 12
    capture_dir, renders = _tiny_capture(tmp_path, rng, width=320, height=288, frames=frames)
    encoder = ChunkEncoder("png")
    for level in (0, 1):
        for frame in range(frames):
            image = read_png(renders / "lod0" / "cam00" / f"{frame:08d}.png")
            image = image if level == 0 else np.clip(image + rng.normal(0, 0.1, image.shape), 0, 1)
            path = chunk_path(tmp_path / "chunked" / f"lod{level}", "cam00", frame // 8 * 8)
            encoder.add(path, frame, np.round(image * 255).astype(np.uint8))
            if frame % 8 == 7 or frame == frames - 1:
                encoder.finish_chunk(path, "cam00", level)
    encoder.close()
    write_manifest(tmp_path / "chunked", {"split": "novel_view", "cameras": ["cam00"], "frames": list(range(frames)),
                                          "levels": [0, 1], "chunk_frames": 8, "codec": "png", "every_view": False})
    torch.manual_seed(0)
    torch.jit.script(_TinyInception()).save(str(tmp_path / "inception.pt"))
    levels = {level: tmp_path / "chunked" / f"lod{level}" for level in (0, 1)}
    cfg = EvaluateConfig(batch_size=5, encode_workers=3)
    results = {}
    for device in ("cpu", "cuda"):
        lpips = copy.deepcopy(LPIPS("vgg", weights="random")).to(device)
        inception = InceptionFeatures(tmp_path / "inception.pt").to(device)
        results[device] = evaluate_levels(Capture.load(capture_dir, cache_mb=0), "novel_view", levels, cfg, lpips,
                                          inception, torch.device(device))
    for level in levels:
        (cpu, cpu_summary), (gpu, gpu_summary) = results["cpu"][level], results["cuda"][level]
        assert cpu["frame"].tolist() == gpu["frame"].tolist() == list(range(frames))
        np.testing.assert_allclose(gpu["psnr"], cpu["psnr"], rtol=0, atol=1e-3)
        np.testing.assert_allclose(gpu["ssim"], cpu["ssim"], rtol=0, atol=1e-4)
        np.testing.assert_allclose(gpu["lpips"], cpu["lpips"], rtol=0, atol=1e-3)
        assert gpu_summary["fid"] == pytest.approx(cpu_summary["fid"], rel=5e-3) and cpu_summary["fid"] > 0
