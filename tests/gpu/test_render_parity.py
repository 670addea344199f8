"""The CPU compositor against gsplat's CUDA rasterizer: images and gradients on random scenes.

Run on the GPU machine (skipped without CUDA). With PIG_PARITY_OUT=path.json set, every scene's
measured differences are added to that JSON file (a list of records).
"""
import json
import math
import os
import tempfile
from pathlib import Path

import pytest
import torch

from pig.render import render_gaussians

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA and gsplat's CUDA extension"),
]

REFERENCE_DEVICE = "cuda"
IMAGE_ATOL = 1e-3
# A (Gaussian, pixel) pair whose alpha lies within float32 rounding of gsplat's 1/255 cut-off
# (gsplat uses __expf) may be kept by one renderer and skipped by the other; that moves the
# pixel by at most 2/255 of the largest colour. Such pixels must stay isolated.
FLIP_BOUND = 2.0 / 255.0
MAX_FLIP_FRACTION = 1e-4
# Expected depth on pixels with alpha > 0.5, in metres: a flipped pair there moves it by at most
# (1/255) * (depth span) / 0.5, again only on isolated pixels.
DEPTH_ATOL = 1e-3
GRAD_RTOL = 1e-2  # ||cpu - gsplat|| / ||gsplat|| per parameter tensor

# (Gaussians, width, height, cameras, SH coefficients K, sh_degree, device the compositor runs on)
SCENES = [
    (1_000, 128, 96, 1, 1, 0, "cpu"),
    (5_000, 256, 192, 2, 4, 1, "cpu"),
    (20_000, 320, 256, 1, 16, 2, "cpu"),
    (20_000, 512, 384, 2, 16, 3, "cpu"),
    (50_000, 512, 512, 1, 16, 3, "cpu"),
    (50_000, 640, 480, 2, 16, 3, "cuda"),
]


def _scene(n, width, height, cameras, bases, seed):
    """Anisotropic Gaussians, most 1-3 px and some up to 30 px across, a few behind the cameras;
    cameras orbit the scene centre."""
    g = torch.Generator().manual_seed(seed)
    focal = 0.9 * width
    z = 2.0 + 3.0 * torch.rand(n, 1, generator=g)
    u = (torch.rand(n, 1, generator=g) * 1.2 - 0.1) * width  # 10% beyond each border
    v = (torch.rand(n, 1, generator=g) * 1.2 - 0.1) * height
    means = torch.cat([(u - width / 2) * z / focal, (v - height / 2) * z / focal, z], dim=1)
    means[: n // 100, 2] *= -1.0  # behind the first camera
    sigma_px = 1.0 + 2.0 * torch.rand(n, 3, generator=g)
    large = torch.rand(n, generator=g) < 0.05
    sigma_px[large] *= 1.0 + 9.0 * torch.rand(int(large.sum()), 1, generator=g)
    scales = sigma_px * z.abs() / focal
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.02 + 0.97 * torch.rand(n, generator=g)
    sh = torch.randn(n, bases, 3, generator=g) * torch.tensor([0.8] + [0.2] * (bases - 1))[:, None]
    centre = torch.tensor([0.0, 0.0, 3.5])
    views, Ks = [], []
    for i in range(cameras):
        angle = 0.35 * i
        rot = torch.tensor(
            [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]]
        )
        view = torch.eye(4)
        view[:3, :3] = rot
        view[:3, 3] = centre - rot @ centre  # p_cam = R (p - c) + c
        views.append(view)
        cx, cy = width / 2 + 3.3 * i, height / 2 - 1.7 * i
        Ks.append(torch.tensor([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]]))
    background = torch.rand(cameras, 3, generator=g)
    return [means, quats, scales, opacities, sh], torch.stack(views), torch.stack(Ks), background


def _render_and_grads(params, views, Ks, width, height, background, sh_degree, backend, weights, mask, device):
    leaves = [p.detach().to(device).requires_grad_(True) for p in params]
    out = render_gaussians(
        *leaves,
        views.to(device),
        Ks.to(device),
        width,
        height,
        background.to(device),
        sh_degree=sh_degree,
        backend=backend,
    )
    w_color, w_alpha, w_depth = (w.to(device) for w in weights)
    loss = (w_color * out.color).sum() + (w_alpha * out.alpha).sum() + (w_depth * out.depth * mask.to(device)).sum()
    loss.backward()
    return [t.detach().cpu() for t in out], [p.grad.cpu() for p in leaves]


def _record(entry):
    path = os.environ.get("PIG_PARITY_OUT")
    if not path:
        return
    path = Path(path)
    records = json.loads(path.read_text()) if path.exists() else []
    records.append(entry)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False) as tmp:
        json.dump(records, tmp, indent=1)
    os.replace(tmp.name, path)


@pytest.mark.parametrize("n,width,height,cameras,bases,sh_degree,device", SCENES)
def test_compositor_matches_gsplat(n, width, height, cameras, bases, sh_degree, device):
    params, views, Ks, background = _scene(n, width, height, cameras, bases, seed=n + width)
    g = torch.Generator().manual_seed(1)
    weights = [torch.rand(cameras, height, width, k, generator=g) for k in (3, 1, 1)]
    weights[2] /= 5.0  # depths are metres (~2-5): keep their share of the loss comparable

    with torch.no_grad():
        on_gpu = [t.to(REFERENCE_DEVICE) for t in (*params, views, Ks)]
        reference = render_gaussians(
            *on_gpu, width, height, background.to(REFERENCE_DEVICE), sh_degree=sh_degree, backend="gsplat"
        )
    mask = (reference.alpha > 0.5).float().cpu()  # ED is ill-conditioned where alpha is tiny
    ref_out, ref_grads = _render_and_grads(
        params, views, Ks, width, height, background, sh_degree, "gsplat", weights, mask, REFERENCE_DEVICE
    )
    out, grads = _render_and_grads(
        params, views, Ks, width, height, background, sh_degree, "cpu", weights, mask, device
    )

    color_diff = (out[0] - ref_out[0]).abs().amax(dim=-1)
    alpha_diff = (out[1] - ref_out[1]).abs()[..., 0]
    pixel_diff = torch.maximum(color_diff, alpha_diff)
    depth_diff = (out[2] - ref_out[2]).abs() * mask
    masked_depth = ref_out[2][mask > 0]
    depth_span = float(masked_depth.max() - masked_depth.min())
    names = ["means", "quats", "scales", "opacities", "sh"]
    rel = {
        name: float((a - b).norm() / b.norm().clamp(min=1e-30)) for name, a, b in zip(names, grads, ref_grads)
    }
    largest = max(float(ref_out[0].abs().max()), float(background.abs().max()), 1.0)
    entry = {
        "gaussians": n,
        "width": width,
        "height": height,
        "cameras": cameras,
        "sh_degree": sh_degree,
        "compositor_device": device,
        "max_abs_color": float(color_diff.max()),
        "max_abs_alpha": float(alpha_diff.max()),
        "pixels_over_1e-3": int((pixel_diff > IMAGE_ATOL).sum()),
        "pixels": pixel_diff.numel(),
        "max_abs_depth_alpha_gt_0.5": float(depth_diff.max()),
        "depth_pixels_over_1e-3": int((depth_diff > DEPTH_ATOL).sum()),
        "depth_span": depth_span,
        "grad_rel": rel,
    }
    _record(entry)

    assert float(ref_out[1].mean()) > 0.2, "scene barely covers the image"
    assert float(pixel_diff.max()) <= FLIP_BOUND * largest + IMAGE_ATOL, entry
    assert int((pixel_diff > IMAGE_ATOL).sum()) <= MAX_FLIP_FRACTION * pixel_diff.numel() + 1, entry
    assert float(depth_diff.max()) <= 2 * FLIP_BOUND * depth_span + DEPTH_ATOL, entry
    assert int((depth_diff > DEPTH_ATOL).sum()) <= MAX_FLIP_FRACTION * pixel_diff.numel() + 1, entry
    for name, value in rel.items():
        assert value <= GRAD_RTOL, (name, entry)
