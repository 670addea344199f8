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
    np.testing.assert_allclose(window.numpy(), ssim_module.TAPS, rtol=1e-15, atol=0)


@pytest.mark.parametrize("form", ["device", "host", "input"])
def test_forms_agree_in_loss_and_gradient(monkeypatch, form):
    monkeypatch.setattr(ssim_module, "BLURS", dict(ssim_module.BLURS))  # use_form replaces "shift" in it
    reference = loss_window_gpu.run_form("constants", 2, 24, 31, 0, "cpu")
    tensor_form = loss_window_gpu.run_form(form, 2, 24, 31, 0, "cpu")
    assert ssim_module.BLURS["shift"] is not ssim_module._blur_shifted
    assert tensor_form["loss"] == pytest.approx(reference["loss"], rel=1e-6)
    assert tensor_form["grad_norm"] == pytest.approx(reference["grad_norm"], rel=1e-6)
