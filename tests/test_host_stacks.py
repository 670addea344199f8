"""benchmarks/host_stacks.py: py-spy's raw stacks of a data-parallel fit read into ranks, threads and frames."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from host_stacks import inclusive, main, own, parse_line, read_ranks  # noqa: E402

SPAWN = '/usr/bin/python3 -c from multiprocessing.spawn import spawn_main; spawn_main(tracker_fd=4, pipe_handle=6) --multiprocessing-fork'
TOP = 'process 100:"python3 benchmarks/fit_multi_gpu.py --gpus 4";process 101:"python3 benchmarks/fit_multi_gpu.py --run 4"'


def line(pid: int, thread: str, frames: list[str], count: int, command: str = SPAWN) -> str:
    return ";".join([TOP, f'process {pid}:"{command}"', f"thread ({pid}): {thread}", *frames]) + f" {count}"


STEP = ["<module> (<string>:1)", "_fit (pig/avatar/training.py:530)"]
LINES = [
    # Rank 1 (the larger pid) first in the file: ranks are numbered by process id.
    line(207, "MainThread", STEP + ["shard_loss (pig/avatar/distributed.py:88)", "_call_impl (torch/nn/modules/module.py:1751)"], 30),
    line(205, "MainThread", STEP + ["shard_loss (pig/avatar/distributed.py:88)", "lpips_views (pig/avatar/losses.py:90)"], 10),
    line(205, "MainThread", STEP + ["backward (torch/_tensor.py:626)"], 50),
    line(205, "Thread-3 (_worker)", ["run (threading.py:1012)", "decode (pig/avatar/batches.py:40)"], 5),
    # Recursion: a frame twice in one stack counts once.
    line(205, "MainThread", STEP + ["walk (pig/body/chain.py:10)", "walk (pig/body/chain.py:10)"], 4),
    # Left out: compilation and the held-out evaluation, and processes that are not ranks.
    line(205, "MainThread", STEP + ["_compile (torch/_dynamo/convert_frame.py:900)"], 70),
    line(207, "MainThread", STEP + ["evaluate_held_out (pig/avatar/training.py:443)", "psnr (pig/avatar/heldout.py:5)"], 9),
    line(207, "MainThread", ["<module> (<string>:1)", "_rank_main (pig/avatar/parallel_fit.py:120)"], 6),
    line(300, "MainThread", ["<module> (torch/_inductor/compile_worker/__main__.py:40)"], 99,
         command="python3 -m torch._inductor.compile_worker"),
    "a line that is no stack",
]


def test_a_raw_line_gives_its_innermost_process_thread_frames_and_count():
    sample = parse_line(LINES[0])
    assert (sample.process, sample.thread, sample.count) == (207, "MainThread", 30)
    assert sample.frames[-2:] == ["shard_loss (pig/avatar/distributed.py)", "_call_impl (torch/nn/modules/module.py)"]
    assert parse_line("no count here") is None


def test_ranks_by_process_id_without_compilation_or_evaluation():
    ranks = read_ranks("\n".join(LINES))
    assert [[s.process for s in samples][0] for samples in ranks.samples] == [205, 207]
    assert sum(s.count for s in ranks.samples[0]) == 69 and sum(s.count for s in ranks.samples[1]) == 30
    assert ranks.left_out == {"torch/_dynamo/convert_frame.py": 70, "evaluate_held_out": 9, "outside the fit": 6}
    main_thread = [s for samples in ranks.samples for s in samples if s.thread == "MainThread"]
    ours = inclusive(main_thread, lambda f: "(pig/" in f)
    assert ours["_fit (pig/avatar/training.py)"] == 94  # every main-thread sample of the steps
    assert ours["shard_loss (pig/avatar/distributed.py)"] == 40
    assert ours["walk (pig/body/chain.py)"] == 4  # not 8
    assert own(main_thread)["backward (torch/_tensor.py)"] == 50


def test_the_tables_print_shares(tmp_path, capsys):
    path = tmp_path / "stacks.txt"
    path.write_text("\n".join(LINES) + "\n")
    assert main([str(path), "--top", "5"]) == 0
    out = capsys.readouterr().out
    assert "| 0 | 205 | MainThread | 64 | 92.8 % |" in out  # 64 of rank 0's 69 samples
    assert "| backward (torch/_tensor.py) | 50 | 53.2 % |" in out  # of the main threads' 94
    assert "| shard_loss (pig/avatar/distributed.py) | 40 | 42.6 % |" in out  # what _fit called
