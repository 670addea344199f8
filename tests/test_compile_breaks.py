"""The compiled fit's graph breaks and recompilations (benchmarks/compile_breaks_cpu.py), counted by Dynamo in each
process: a data-parallel fit on two gloo processes against one process, with the GPU benchmarks' step timer
(fit_gpu.PhaseTimer) turned on mid-fit as `fit_multi_gpu.py --profile-phases` turns it on."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from compile_breaks_cpu import run  # noqa: E402

ITERATIONS = 4
PROFILE_FROM = 2  # the timer on for the last two iterations


def test_step_timer_and_data_parallel_fit_add_no_graph_break_or_recompilation(small_capture, tmp_path):
    # Dynamo's tracing alone (the eager backend): its breaks and guards are those of any backend, in seconds.
    [one] = run(tmp_path, small_capture, 1, ITERATIONS, None, "eager")
    two = run(tmp_path, small_capture, 2, ITERATIONS, PROFILE_FROM, "eager")
    assert one["graph_breaks"] == 0 and one["graphs"] >= 3  # decoders, posing, loss: each compiled whole
    # Two ranks with the timer on mid-fit: no break, and each rank compiles no more than one process without the
    # timer (rank 1 less: rank 0 alone evaluates, without grad). The timer's module hooks ran inside the compiled
    # regions: their clock read broke the posing graph and their `active` flag, guarded, recompiled every graph when
    # profiling began (before the fix: 5 breaks on each rank, 11 and 9 graphs against 6).
    assert [r["graph_breaks"] for r in two] == [0, 0], [r["break_reasons"] for r in two]
    for rank in two:
        assert rank["graphs"] <= one["graphs"] and rank["recompiles"] <= one["recompiles"], rank["recompiled"]
    # The timer still times the model's parts that run outside a compiled region.
    assert all({"model.grid", "model.decoders", "model.anchor_solve"} <= set(r["phases"]) for r in two)
