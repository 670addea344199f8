"""Shared fixtures. Tests run on the CPU in float64 where they compare against references."""
import os
import signal

import pytest
import torch

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))

# Some tests press Ctrl-C (SIGINT to a child's process group) or rely on torch's spawn ending a fit's ranks with
# SIGINT when their parent dies. A session started as a background job of a non-interactive shell (`nohup pytest &`
# in a script) inherits SIGINT ignored, and so would every process it starts, where Ctrl-C then does nothing:
# handle it again here, so that the processes the tests start begin with its default action, as in a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def rng():
    import numpy as np

    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory):
    """A preprocessed synthetic capture (5 cameras x 4 frames at 48 px) for fit and render-stage tests."""
    from pig.data.synthetic import SyntheticConfig, generate_capture
    from pig.stages.preprocess import main as preprocess

    root = tmp_path_factory.mktemp("smallcap")
    raw = generate_capture(root / "raw", SyntheticConfig(cameras=5, frames=4, width=48, height=48, workers=1), progress=False)
    out = root / "capture"
    preprocess(["--input", str(raw), "--output", str(out), "--preset", "test", "--format", "thuman4",
                "--body-model", str(raw / "body_model.npz"), "--no-progress"])
    return out


@pytest.fixture(scope="session")
def tiny_fit(small_capture, tmp_path_factory):
    """(capture folder, avatar.pt) of a 3-iteration fit of `small_capture` with the test preset."""
    from pig.avatar.training import fit
    from pig.config import derive_preset

    root = tmp_path_factory.mktemp("tinyfit")
    derive_preset(root / "preset.yaml", "test", fit={"iterations": 3, "eval_every": 3, "checkpoint_minutes": 0.0})
    return small_capture, fit(small_capture, root / "pig", str(root / "preset.yaml"))

