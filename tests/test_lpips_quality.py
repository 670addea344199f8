"""benchmarks/lpips_quality.py at toy size with random LPIPS weights: two fits of equal training time, with and
without the term, each scored by the render and evaluate stages, and the difference table."""
import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "lpips_quality.py"


def _rows(text: str, title: str) -> dict[tuple[str, int], list[float]]:
    block = text.split(title, 1)[1].split("\n\n", 1)[0]
    return {(m[1], int(m[2])): [float(v) for v in m[3].split(" | ")]
            for m in re.finditer(r"^\| (novel_\w+) \| (\d+) \| \d* \| (.+) \|$", block, re.M)}


@pytest.mark.slow
def test_lpips_quality_runs_both_fits_and_prints_their_tables(small_capture, tmp_path):
    env = {**os.environ, "TORCH_HOME": str(tmp_path / "no_weights"), "PYTHONPATH": str(SCRIPT.parents[1])}
    settings = ("fit.lpips_net=alex,fit.lpips_form=mmlphuman,fit.lpips_crop=32,fit.eval_every=1000,avatar.num_anchors=300,"
                "rasterizer.backend=cpu,evaluate.device=cpu,evaluate.timing_frames=1,fit.cpu_threads=1")
    out = subprocess.run([sys.executable, str(SCRIPT), "--capture", str(small_capture), "--workdir", str(tmp_path / "w"),
                          "--preset", "test", "--budget", "2", "--device", "cpu", "--lpips-weights", "random",
                          "--finest-only", "--set", settings], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    text = out.stdout
    with_term = re.search(r"with_lpips: (\d+) iterations, LPIPS term 'random weights'", text)
    without = re.search(r"without_lpips: (\d+) iterations, LPIPS term 'weight 0'", text)
    assert with_term and without and int(with_term[1]) > 0 and int(without[1]) > 0
    on, off = _rows(text, "with_lpips: "), _rows(text, "without_lpips: ")
    diff = _rows(text, "with_lpips - without_lpips")
    assert set(on) == set(off) == set(diff) == {("novel_view", 1), ("novel_pose", 1)}
    for key in diff:
        psnr_on, ssim_on, _ = on[key]
        assert 0 < ssim_on <= 1 and psnr_on > 5
        assert diff[key][:2] == pytest.approx([psnr_on - off[key][0], ssim_on - off[key][1]], abs=2e-4)
        assert str(on[key][2]) == "nan"  # the evaluation's LPIPS weights are absent: missing, not a number
    # Each fit's own training log: the term on every step row of one, on none of the other's.
    logs = {name: pd.read_csv(tmp_path / "w" / f"fit_{name}" / "train_log.csv").iloc[1:] for name in ("with_lpips", "without_lpips")}
    assert (logs["with_lpips"]["lpips"] > 0).all() and logs["without_lpips"]["lpips"].isna().all()
    assert len(logs["with_lpips"]) > 0 and len(logs["without_lpips"]) > 0
