"""A CPU fit at a fixed thread count is bit-identical from run to run, and across a kill and resume (DESIGN.md 7).

The anchors are enough (6000) for the transport's gather backward to exceed torch's parallel grain size (32768
elements), where two threads used to add into shared vertices in a racing order.
"""
import pandas as pd
import pytest
import torch

from pig.config import derive_preset, load_preset

LOG_METRICS = ["iteration", "lod", "loss", "l1", "ssim", "lpips", "lpips_term", "heldout_psnr", "heldout_psnr_iterate"]


def _preset(tmp_path) -> str:
    return str(derive_preset(tmp_path / "preset.yaml", "test", avatar={"num_anchors": 6000},
                             fit={"iterations": 4, "eval_every": 4, "checkpoint_minutes": 0.0, "views": 2}))


def _workflow_threads() -> list[int]:
    """The fit rule's threads in each preset (what the workflow passes as --threads), and 1 (`--set-threads`)."""
    counts = {1}
    for name in ("test", "cpu-demo"):
        resources = load_preset(name).get("resources", {})
        counts.add(int(resources.get("fit_avatar", resources.get("default", {})).get("threads", 1)))
    return sorted(counts, reverse=True)


def _assert_same_fit(a_dir, b_dir):
    a, b = (torch.load(d / "avatar.pt", weights_only=True)["model"] for d in (a_dir, b_dir))
    assert a.keys() == b.keys()
    differ = [key for key in a if not torch.equal(a[key], b[key])]
    assert not differ, f"{len(differ)} of {len(a)} tensors differ: {differ[:5]}"
    logs = [pd.read_csv(d / "train_log.csv", keep_default_na=False) for d in (a_dir, b_dir)]
    pd.testing.assert_frame_equal(logs[0][LOG_METRICS], logs[1][LOG_METRICS], check_exact=True)


def fill_setting() -> bool:
    return torch.utils.deterministic.fill_uninitialized_memory


class _Killed(Exception):
    pass


@pytest.mark.slow
def test_two_cpu_fits_and_a_resumed_one_are_bit_identical(small_capture, tmp_path, monkeypatch):
    """The second fit runs with deterministic mode's NaN fill of new tensors, which the CPU fit leaves out (~5 % of a
    step): a guard against kernels that read uninitialised memory, so its weights must be the same."""
    import pig.avatar.training as training

    assert 2 in _workflow_threads()  # the CPU default's fit rule runs two threads: the case that raced
    preset = _preset(tmp_path)
    before = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(), fill_setting()
    unfilled = training.use_deterministic_kernels

    def with_fill(device, requested):
        unfilled(device, requested)
        torch.utils.deterministic.fill_uninitialized_memory = True

    for threads in _workflow_threads():
        root = tmp_path / f"threads{threads}"
        fills = []
        training.fit(small_capture, root / "a", preset, threads=threads, on_iteration=lambda i: fills.append(fill_setting()))
        assert fills and not any(fills)
        if threads > 1:
            with monkeypatch.context() as patch:
                patch.setattr(training, "use_deterministic_kernels", with_fill)
                training.fit(small_capture, root / "b", preset, threads=threads)
            _assert_same_fit(root / "a", root / "b")

        def kill_at_2(iteration):
            if iteration == 2:
                raise _Killed

        with pytest.raises(_Killed):
            training.fit(small_capture, root / "resumed", preset, threads=threads, on_iteration=kill_at_2)
        training.fit(small_capture, root / "resumed", preset, threads=threads)
        _assert_same_fit(root / "a", root / "resumed")
    # The caller's settings come back after each fit.
    assert (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(), fill_setting()) == before
