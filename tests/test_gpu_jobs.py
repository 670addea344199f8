"""benchmarks/gpu_jobs.py: the replay of a run's jobs in another order, against schedules worked out by hand, and
its per-GPU table from a job table and nvidia-smi samples."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from gpu_jobs import ORDERS, main, read_jobs, replay  # noqa: E402

HEAD = ("| job | rule | wildcards | start | end | s | status | slot held (UTC) | CUDA_VISIBLE_DEVICES |\n"
        "|---|---|---|---|---|---|---|---|---|\n")


def row(job: int, rule: str, wildcards: str, start: str, end: str, seconds: int, device: str) -> str:
    return f"| {job} | {rule} | {wildcards} | {start} | {end} | {seconds} | done |  | {device} |\n"


def three_variants() -> str:
    """Fits of 10 s, one split each: a render of 1 s and an evaluation of 2 s, then the table (0 s, no GPU)."""
    text = HEAD
    for n, variant in enumerate("abc"):
        text += row(3 * n, "fit_avatar", f"subject=s, variant={variant}", "10:00:00", "10:00:10", 10, "0")
        text += row(3 * n + 1, "render_split", f"subject=s, variant={variant}, split=v", "10:00:10", "10:00:11", 1,
                    "0")
        text += row(3 * n + 2, "evaluate", f"subject=s, variant={variant}, split=v", "10:00:11", "10:00:13", 2, "0")
    return text + row(9, "make_tables", "dataset=d", "10:00:13", "10:00:13", 0, "-")


def test_replay_matches_the_schedules_worked_by_hand(tmp_path):
    table = tmp_path / "jobs.md"
    table.write_text(three_variants())
    jobs = read_jobs([table])
    # 2 GPUs, downstream first: fits a, b (0-10); renders a, b (10-11); evaluations (11-13); fit c (13-23); its
    # render (23-24) and evaluation (24-26). Fits first: fit c and render a at 10; render b 11-12; evaluation a
    # 12-14, b 14-16 beside fit c (10-20); render c 20-21, evaluation c 21-23.
    assert replay(jobs, 2, ORDERS["downstream first"]) == pytest.approx(26)
    assert replay(jobs, 2, ORDERS["fits first"]) == pytest.approx(23)
    for order in ORDERS.values():  # one GPU: every GPU second one after another
        assert replay(jobs, 1, order) == pytest.approx(3 * (10 + 1 + 2))
    # Enough GPUs: the longest chain
    assert replay(jobs, 9, ORDERS["downstream first"]) == pytest.approx(13)


def test_a_job_waits_for_its_input_whatever_the_rows_order(tmp_path):
    table = tmp_path / "jobs.md"
    table.write_text(HEAD + row(1, "render_split", "variant=a, split=v", "10:00:00", "10:00:01", 1, "0")
                     + row(2, "fit_avatar", "variant=a", "10:00:01", "10:00:02", 1, "0")
                     + row(3, "fit_avatar", "variant=b", "10:00:01", "10:00:02", 1, "0"))
    jobs = read_jobs([table])  # the render's row first; no preprocess row: the fits wait for nothing
    assert replay(jobs, 1, ORDERS["downstream first"]) == pytest.approx(3)
    assert replay(jobs, 2, ORDERS["downstream first"]) == pytest.approx(2)  # both fits, then the render


def test_per_gpu_table_from_jobs_and_samples(tmp_path, capsys):
    table = tmp_path / "jobs.md"
    table.write_text(HEAD + row(1, "fit_avatar", "variant=a", "10:00:00", "10:00:10", 10, "0")
                     + row(2, "fit_avatar", "variant=b", "10:00:00", "10:00:05", 5, "1"))
    smi = tmp_path / "smi.csv"
    smi.write_text("timestamp, index, utilization.gpu [%], memory.used [MiB]\n"
                   + "".join(f"2026/11/27 10:00:{s:02d}.000, {gpu}, {util} %, {mem} MiB\n"
                             for s in (2, 8) for gpu, util, mem in ((0, 80, 100 + s), (1, 0 if s > 5 else 40, 50)))
                   + "2026/11/27 10:05:00.000, 0, 100 %, 9999 MiB\n")  # after the window: not counted
    assert main([str(table), "--smi", str(smi), "--gpus", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "| 0 | 1 | 10 | 100% | 80 | 108 |" in lines
    assert "| 1 | 1 | 5 | 50% | 20 | 50 |" in lines


def test_no_job_rows_is_an_error_naming_the_file(tmp_path):
    table = tmp_path / "empty.md"
    table.write_text("nothing here\n")
    with pytest.raises(SystemExit, match="empty.md"):
        read_jobs([table])
