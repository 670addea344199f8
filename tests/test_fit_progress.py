"""Watching a fit: progress lines (iteration, loss, held-out PSNR, time left), TensorBoard scalars read back from the
event file, train_log.png redrawn at each held-out evaluation, and a video writer that prints no false warning."""
import io
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from preset_files import write_test_preset

from pig.avatar.fit_progress import FitProgress
from pig.progress import set_quiet

REPO = Path(__file__).resolve().parents[1]


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def _progress(start=0, total=100, interval=10.0):
    stream, clock = io.StringIO(), Clock()
    return FitProgress("out/pig", total, start, interval, stream=stream, clock=clock), stream, clock


def test_lines_come_every_interval_and_at_evaluations_with_the_time_left():
    progress, stream, clock = _progress()
    progress.record({"iteration": 0, "loss": "", "heldout_psnr": 12.5})
    clock.now = 4.0
    progress.record({"iteration": 10, "loss": 0.25, "heldout_psnr": ""})
    progress.step(10, 0.10)
    assert stream.getvalue() == ""  # 4 s < 10 s, no evaluation
    clock.now = 50.0
    progress.record({"iteration": 25, "loss": 0.125, "heldout_psnr": ""})
    progress.step(25, 0.25)
    # 25 iterations in 50 s; a quarter done in 50 s leaves 150 s.
    assert stream.getvalue() == ("fit out/pig: iteration 25/100 (25.0 %), loss 0.125, held-out PSNR 12.50 dB "
                                 "(iteration 0), 0.5 it/s, 0:02:30 left\n")
    clock.now = 52.0
    progress.record({"iteration": 26, "loss": 0.1, "heldout_psnr": 20.0})
    progress.step(26, 0.26, evaluated=True)  # an evaluation prints at once
    assert stream.getvalue().splitlines()[-1].startswith("fit out/pig: iteration 26/100 (26.0 %), loss 0.1, "
                                                         "held-out PSNR 20.00 dB (iteration 26)")
    progress.print_line(100, 1.0)
    assert stream.getvalue().splitlines()[-1].endswith(", done")


def test_a_resumed_fit_estimates_from_this_runs_pace_and_quiet_prints_nothing():
    progress, stream, clock = _progress(start=50)
    clock.now = 20.0
    progress.step(60, 0.60)
    # 10 % of the run in 20 s: 40 % left takes 80 s.
    assert stream.getvalue().rstrip().endswith("loss -, held-out PSNR -, 0.5 it/s, 0:01:20 left")
    set_quiet(True)
    try:
        clock.now = 100.0
        progress.step(90, 0.9)
        assert stream.getvalue().count("\n") == 1
    finally:
        set_quiet(False)


@pytest.mark.slow
def test_fit_prints_progress_writes_tensorboard_and_redraws_the_plot(small_capture, tmp_path, capsys, monkeypatch):
    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed (pip install '.[tensorboard]')")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from pig.avatar import training

    drawn = []
    plot = training.plot_train_log
    monkeypatch.setattr(training, "plot_train_log",
                        lambda path, rows, title="": (drawn.append(len(rows)), plot(path, rows, title)))
    out = tmp_path / "pig"
    preset = write_test_preset(tmp_path, iterations=4, eval_every=2, checkpoint_minutes=1e6)
    training.fit(small_capture, out, preset, progress_s=1e6, tensorboard=True)
    log = pd.read_csv(out / "train_log.csv")
    evaluated = log[log["heldout_psnr"].notna()]
    assert evaluated["iteration"].tolist() == [0, 2, 4]
    # The plot: drawn at each evaluation (with the rows up to it), the last one the end's with every row.
    rows_at = [int((log["iteration"] <= i).sum()) for i in evaluated["iteration"]]
    assert drawn == rows_at and rows_at[-1] == len(log)
    # The lines: one at the start and one at each evaluation, the last one the end's (the interval never passes).
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith(f"fit {out}: ")]
    assert len(lines) == 3
    for line, (_, row) in zip(lines, evaluated.iterrows()):
        assert f"iteration {int(row['iteration'])}/4 " in line
        assert f"held-out PSNR {row['heldout_psnr']:.2f} dB (iteration {int(row['iteration'])})" in line
    assert f", loss {log['loss'].iloc[-1]:.4g}," in lines[-1] and lines[-1].endswith(", done")
    assert f", loss {log.loc[log['iteration'] == 2, 'loss'].item():.4g}," in lines[1]
    assert " left" in lines[1] and "it/s" in lines[1]
    # TensorBoard: the logged rows' loss and every held-out PSNR, by iteration.
    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    assert {"train/loss", "train/l1", "heldout/psnr"} <= set(events.Tags()["scalars"])
    losses = {e.step: e.value for e in events.Scalars("train/loss")}
    trained = log[log["loss"].notna()]
    assert sorted(losses) == trained["iteration"].tolist()
    for _, row in trained.iterrows():
        assert losses[int(row["iteration"])] == pytest.approx(row["loss"], rel=1e-6)
    psnrs = {e.step: e.value for e in events.Scalars("heldout/psnr")}
    assert psnrs == pytest.approx(dict(zip(evaluated["iteration"], evaluated["heldout_psnr"])), rel=1e-6)


def test_tensorboard_missing_is_a_clear_error(monkeypatch):
    from pig.avatar.fit_progress import tensorboard_writer

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # an import of it now fails
    with pytest.raises(ImportError, match=r"pip install 'pig\[tensorboard\]'"):
        tensorboard_writer(Path("unused"))


def test_video_writer_prints_no_false_codec_warning_and_passes_other_output_on(tmp_path):
    """OpenCV's 'tag ... is not supported ... webm' line is a false alarm (the VP9 video is fine): kept off stderr,
    while anything else written to stderr meanwhile still arrives. In a child process: the line is written by
    OpenCV's C code to file descriptor 2, which pytest's capture does not see."""
    script = f"""
import os
import cv2
import numpy as np
from pig.avatar import animation
from pig.avatar.animation import VideoWriter

open_writer = cv2.VideoWriter
def noisy(*args):
    os.write(2, b"another message\\n")
    return open_writer(*args)
animation.cv2.VideoWriter = noisy
writer = VideoWriter({str(tmp_path / 'v.webm')!r}, 10.0, 32, 24)
for i in range(3):
    writer.write(np.full((24, 32, 3), i / 3))
writer.close()
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stderr == "another message\n"
    import cv2

    video = cv2.VideoCapture(str(tmp_path / "v.webm"))
    frames = 0
    while video.read()[0]:
        frames += 1
    assert frames == 3 and int(video.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") == b"VP90"
