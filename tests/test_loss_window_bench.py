"""benchmarks/loss_window_gpu.py: the earlier codes' SSIM windows it rebuilds are the loss's window, and its
forms give one loss and gradient (the benchmark compares their memory and time, so they must compute the same)."""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import loss_window_gpu  # noqa: E402
from pig.metrics import ssim as ssim_module  # noqa: E402


@pytest.mark.parametrize("where", ["device", "host"])
def test_rebuilt_windows_are_the_taps(where):
    window = loss_window_gpu.window_made_on(where, torch.float64, torch.device("cpu"))
    offsets = np.arange(-5, 6, dtype=np.float64)
    weights = np.exp(-0.5 * (offsets / 1.5) ** 2)
    np.testing.assert_allclose(window.numpy(), weights / weights.sum(), rtol=1e-15, atol=0)
    assert torch.equal(window, ssim_module.gaussian_window(torch.float64, "cpu"))


@pytest.mark.parametrize("form", ["constants", "device", "host"])
def test_forms_agree_in_loss_and_gradient(monkeypatch, form):
    monkeypatch.setattr(ssim_module, "BLURS", dict(ssim_module.BLURS))  # use_form replaces "shift" in it
    reference = loss_window_gpu.run_form("input", 2, 24, 31, 0, "cpu")  # this code's form
    assert ssim_module.BLURS["shift"] is ssim_module._blur_shifted
    earlier = loss_window_gpu.run_form(form, 2, 24, 31, 0, "cpu")
    assert ssim_module.BLURS["shift"] is not ssim_module._blur_shifted
    assert earlier["loss"] == pytest.approx(reference["loss"], rel=1e-6)
    assert earlier["grad_norm"] == pytest.approx(reference["grad_norm"], rel=1e-6)
