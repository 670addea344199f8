"""The LPIPS term's fast path on CUDA: MMLPHuman's fixed-shape crop against its sliced twin, and TrainingLPIPS (bf16
backbone and head, compiled) against the float32 reference `LPIPS.forward`, VGG with random weights.

Run on the GPU machine (skipped without CUDA). The crops: the same bilinear weights from float64 positions, float32
rounding only (bound 1e-6 on values in [0, 1]). The distances: bf16 keeps 8 bits of mantissa, bound 2 % relative,
and the gradient's direction within cosine 0.99 of the reference's."""
import pytest
import torch
from torch._dynamo.utils import counters

from pig.avatar.lpips_crop import crop_views, crop_views_sliced
from pig.metrics.lpips import LPIPS, TrainingLPIPS

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


def _views(count=4, height=1150, width=1330):
    gen = torch.Generator(device="cuda").manual_seed(0)
    images = torch.rand(count, 3, height, width, generator=gen, device="cuda")
    masks = torch.zeros(count, height, width, dtype=torch.bool, device="cuda")
    for k, (top, left, bottom, right) in enumerate([(100, 400, 1049, 800), (0, 0, 300, 200), (500, 600, 700, 650),
                                                    (0, 300, 1149, 1329)][:count]):
        masks[k, top:bottom + 1, left:right + 1] = True
    return images, masks


@pytest.mark.parametrize("windows", [False, True])
def test_fixed_shape_crop_matches_the_sliced_crop_on_cuda(windows):
    images, masks = _views()
    offsets = torch.rand(4, 2, device="cuda", dtype=torch.float64) if windows else None
    background = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    fixed, valid = crop_views(images, masks, background, 512, offsets)
    sliced, valid_sliced = crop_views_sliced(images, masks, background, 512, offsets)
    assert valid.tolist() == valid_sliced.tolist() == [True] * 4
    torch.testing.assert_close(fixed, sliced, rtol=0, atol=1e-6)


def test_compiled_bf16_lpips_matches_the_float32_reference_on_cuda():
    net = LPIPS("vgg", weights="random", seed=0).cuda()
    gen = torch.Generator(device="cuda").manual_seed(1)
    x = torch.rand(4, 3, 512, 512, generator=gen, device="cuda")
    y = (x + 0.1 * torch.randn(4, 3, 512, 512, generator=gen, device="cuda")).clamp(0, 1)
    reference = net(x, y)
    graphs = counters["stats"]["unique_graphs"]
    fast = TrainingLPIPS(net, bf16=True, bf16_head=True, compiled=True)
    xg = x.clone().requires_grad_(True)
    for _ in range(3):
        value = fast(xg, y)
        (grad,) = torch.autograd.grad(value.sum(), xg)
    assert counters["stats"]["unique_graphs"] == graphs + 1
    assert ((value - reference).abs() / reference).max() < 0.02
    xr = x.clone().requires_grad_(True)
    (reference_grad,) = torch.autograd.grad(net(xr, y).sum(), xr)
    cosine = torch.nn.functional.cosine_similarity(grad.flatten(), reference_grad.flatten(), dim=0)
    assert cosine > 0.99
