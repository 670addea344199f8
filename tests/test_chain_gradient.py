"""The full chain's gradient against finite differences, in float64 (DESIGN.md 8): latent grid, preconditioned
anchors, body refiner, body model, transport (Eqs. 2-3), decoders (Eqs. 6-11) and the CPU compositor.

Each part has its own gradient check; this one holds the composition: the autograd directional derivative of a
rendered loss along a random direction in every parameter equals the central difference of the loss.
"""
import numpy as np
import torch

from pig.body.params import SmplxParams
from pig.render.api import render_gaussians
from avatar_fixture import small_avatar


def test_directional_derivative_of_a_render_matches_central_differences(tmp_path):
    from pig.body.standin import write_standin

    write_standin(tmp_path / "body_model.npz")
    rng = np.random.default_rng(3)
    params = SmplxParams(rng.normal(scale=0.2, size=(2, 55, 3)), np.zeros(10), np.zeros((2, 10)), np.zeros((2, 3)))
    model = small_avatar((tmp_path / "body_model.npz").read_bytes(), params, True, num_anchors=60, levels=2,
                         sh_degree=1, hidden_layers=1, hidden_width=8).double()
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # down -z at a y-up body
    viewmat[2, 3] = 3.0
    K = torch.tensor([[12.0, 0, 8], [0, 12.0, 8], [0, 0, 1]], dtype=torch.float64)
    weights = torch.rand(1, 16, 16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss() -> torch.Tensor:
        g = model(torch.tensor([1]), lod=1)
        out = render_gaussians(g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0], viewmat[None], K[None],
                               16, 16, torch.zeros(3, dtype=torch.float64), backend="cpu")
        return (out.color * weights).sum() + out.depth.mean()

    parameters = [p for p in model.parameters() if p.requires_grad]
    groups = {"grid": model.grid, "anchors": model.anchors, "decoder": model.decoder, "refiner": model.refiner}
    assert all(any(p.requires_grad for p in part.parameters()) for part in groups.values())
    model.zero_grad()
    value = loss()
    value.backward()
    assert value.item() > 0
    gen = torch.Generator().manual_seed(1)
    direction = [torch.randn(p.shape, generator=gen, dtype=torch.float64) for p in parameters]
    for part, module in groups.items():  # each part's own share of the derivative is non-zero: all of it is checked
        share = sum((p.grad * d).sum() for p, d in zip(parameters, direction)
                    if p.grad is not None and any(p is q for q in module.parameters()))
        assert abs(float(share)) > 1e-8, part
    analytic = sum((p.grad * d).sum() for p, d in zip(parameters, direction) if p.grad is not None).item()
    eps = 1e-6
    with torch.no_grad():
        for p, d in zip(parameters, direction):
            p.add_(eps * d)
        plus = loss().item()
        for p, d in zip(parameters, direction):
            p.sub_(2 * eps * d)
        minus = loss().item()
    numeric = (plus - minus) / (2 * eps)
    assert abs(analytic - numeric) <= 1e-6 * max(1.0, abs(numeric)), (analytic, numeric)
