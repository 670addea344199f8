"""fit.compile_mode: torch.compile's mode reaches every compiled region of a training step (decoders, posing,
L1 + SSIM, LPIPS network), and with "reduce-overhead" each iteration begins a new step of torch's CUDA-graph trees
(so a step's graph outputs are never read after the next step's replays overwrote them)."""
import pytest
import torch

from pig.avatar.fit_config import FitConfig
from pig.avatar.training import fit
from pig.config import ConfigError, derive_preset

ITERATIONS = 3


def _fit_recording(capture, root, monkeypatch, mode: str) -> tuple[dict[str, str], int]:
    """A 3-iteration fit of the test preset with every compile switch on and torch.compile replaced by a recorder
    that returns the function as it is (eager, so the test compiles nothing): {compiled function: mode} and the
    number of CUDA-graph step marks."""
    modes: dict[str, str] = {}
    marks = []

    def recorder(fn, *args, mode=None, **kwargs):
        modes[getattr(fn, "__name__", repr(fn))] = mode
        return fn

    monkeypatch.setattr(torch, "compile", recorder)
    monkeypatch.setattr(torch.compiler, "cudagraph_mark_step_begin", lambda: marks.append(1))
    derive_preset(root / "preset.yaml", "test",
                  fit={"iterations": ITERATIONS, "eval_every": ITERATIONS, "checkpoint_minutes": 0.0, "compile": True,
                       "compile_posing": True, "lpips_compile": True, "weight_lpips": 0.1, "lpips_weights": "random",
                       "lpips_net": "alex", "lpips_crop": 32, "compile_mode": mode})
    fit(capture, root / "fit", str(root / "preset.yaml"))
    return modes, len(marks)


@pytest.mark.parametrize("mode", ["default", "reduce-overhead"])
def test_compile_mode_reaches_every_compiled_region(small_capture, tmp_path, monkeypatch, mode):
    modes, marks = _fit_recording(small_capture, tmp_path, monkeypatch, mode)
    regions = {"_run_mlps", "_posed_splats_sync_free", "<lambda>", "_eager"}  # decoders, posing, L1 + SSIM, LPIPS
    assert regions <= set(modes), modes
    assert {modes[name] for name in regions} == {mode}
    assert marks == (ITERATIONS if mode == "reduce-overhead" else 0)


def test_compile_mode_is_validated():
    with pytest.raises(ConfigError, match="fit.compile_mode"):
        FitConfig(compile_mode="max-autotune")
