"""benchmarks/fit_multi_gpu.py and benchmarks/kernel_profile.py: the kernel profile's interval arithmetic, whole and
by phase, against a brute-force count on synthetic traces, its reading of a real (CPU) profiler trace, the phases'
annotations in the profiled iterations only, `--collect` over the run folders found, partial ones included, and the
parity rules (fit_multi_gpu.py's over held-out PSNRs, parity_trajectory.py's over step-after-step losses)."""
import functools
import json
import os
import random
import shutil
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from kernel_profile import (BACKWARD_OP, ITERATION, PHASE, Row, Trace, bus_bandwidth_gbs,  # noqa: E402
                            chrome_trace_rows, clip, phase_verdict, split_trace, summarise, summarise_phases,
                            trace_rows, union_length)

with mock.patch.dict(os.environ):  # the benchmark sets NCCL's variables for its own processes, not this one's
    import fit_multi_gpu  # noqa: E402

SPAN = 300  # synthetic traces live on the integer grid [0, SPAN) ns


def _cells(intervals, lo=0, hi=SPAN) -> np.ndarray:
    """Brute force: the grid's unit cells [t, t + 1) that some interval covers, within [lo, hi)."""
    covered = np.zeros(SPAN, dtype=bool)
    for start, end in intervals:
        covered[max(start, lo):min(end, hi)] = True
    covered[:lo] = covered[hi:] = False
    return covered


def _intervals(rng: random.Random, count: int, longest: int = 40) -> list[tuple[int, int]]:
    out = []
    for _ in range(count):
        start = rng.randrange(SPAN)
        out.append((start, min(SPAN, start + rng.randrange(0, longest))))  # some empty
    return out


@pytest.mark.parametrize("seed", range(20))
def test_union_and_clip_against_cell_count(seed):
    rng = random.Random(seed)
    intervals = _intervals(rng, rng.randrange(0, 30))
    assert union_length(intervals) == _cells(intervals).sum()
    lo, hi = sorted(rng.sample(range(SPAN + 1), 2))
    assert union_length(clip(intervals, lo, hi)) == _cells(intervals, lo, hi).sum()


@pytest.mark.parametrize("seed", range(20))
def test_summary_against_cell_count(seed):
    rng = random.Random(seed)
    cuts = sorted(rng.sample(range(10, SPAN - 10), rng.randrange(1, 6)))
    windows = list(zip([5] + cuts, cuts + [SPAN - 5]))  # consecutive iterations, as the profiler's annotations
    names = ["ncclDevKernel_AllReduce_Sum_f32_RING_LL", "ncclDevKernel_Broadcast_RING_LL", "triton_poi_fused_0",
             "void at::native::vectorized_elementwise_kernel", "rasterize_to_pixels_fwd"]
    kernels = [(s, e, rng.choice(names)) for s, e in _intervals(rng, rng.randrange(0, 40))]
    host = _intervals(rng, rng.randrange(0, 30))
    waits = _intervals(rng, rng.randrange(0, 8))
    got = summarise(Trace(windows, kernels, host, waits), top=3)

    n = len(windows)
    expect = dict.fromkeys(["wall_ms", "gpu_busy_ms", "nccl_ms", "compute_ms", "nccl_alone_ms", "all_reduce_ms",
                            "host_ms", "host_wait_ms", "kernels"], 0.0)
    totals: dict[str, list] = {}
    for lo, hi in windows:
        busy = _cells([(s, e) for s, e, _ in kernels], lo, hi)
        nccl = _cells([(s, e) for s, e, name in kernels if name.startswith("nccl")], lo, hi)
        compute = _cells([(s, e) for s, e, name in kernels if not name.startswith("nccl")], lo, hi)
        waiting = _cells(waits, lo, hi)
        expect["wall_ms"] += hi - lo
        expect["gpu_busy_ms"] += busy.sum()
        expect["nccl_ms"] += nccl.sum()
        expect["compute_ms"] += compute.sum()
        expect["nccl_alone_ms"] += (nccl & ~compute).sum()
        expect["all_reduce_ms"] += _cells([(s, e) for s, e, name in kernels if "AllReduce" in name], lo, hi).sum()
        expect["host_ms"] += (_cells(host, lo, hi) & ~waiting).sum()
        expect["host_wait_ms"] += waiting.sum()
        for s, e, name in kernels:
            if lo <= s < hi:
                expect["kernels"] += 1
                totals.setdefault(name, [0, 0])
                totals[name][0] += e - s
                totals[name][1] += 1
    for key, value in expect.items():  # means per iteration; the grid's ns in ms
        assert got[key] == pytest.approx(value / n * (1e-6 if key.endswith("_ms") else 1), abs=1e-12), key
    assert got["iterations"] == n
    assert got["gpu_idle"] == pytest.approx(1 - expect["gpu_busy_ms"] / expect["wall_ms"])
    ranked = sorted(totals.items(), key=lambda item: (-item[1][0], item[0]))[:3]
    assert got["top_kernels"] == [[name, pytest.approx(ns * 1e-6 / n), pytest.approx(k / n)]
                                  for name, (ns, k) in ranked]


def test_split_trace_keeps_the_steps_threads():
    main, backward, loader = 11, 12, 13
    rows = [Row("user_annotation", ITERATION, 0, 100, main, 1, 0),
            Row("user_annotation", ITERATION, 100, 200, main, 2, 0),
            Row("user_annotation", "something else", 0, 300, main, 3, 0),
            Row("cpu_op", "aten::mul", 10, 20, main, 4, 0),
            Row("cpu_op", "autograd::engine::evaluate_function: MulBackward0", 30, 40, backward, 5, 0),
            Row("cpu_op", "aten::copy_", 50, 60, loader, 6, 0),  # the view loader's staging: not the step's
            Row("cuda_runtime", "cudaStreamSynchronize", 12, 18, 99, 7, 4),  # linked to the main thread's op
            Row("cuda_runtime", "cudaStreamSynchronize", 52, 58, 99, 8, 6),  # to the loader's
            Row("cuda_runtime", "cudaLaunchKernel", 14, 15, 99, 9, 4),  # a launch does not wait
            Row("kernel", "triton_poi_fused_0", 15, 25, 0, 10, 9),
            Row("gpu_memcpy", "Memcpy HtoD", 25, 35, 0, 11, 0)]
    trace = split_trace(rows)
    assert trace.windows == [(0, 100), (100, 200)]
    assert sorted(trace.host_ops) == [(10, 20), (30, 40)]
    assert trace.waits == [(12, 18)]
    assert trace.kernels == [(15, 25, "triton_poi_fused_0")]


def test_chrome_trace_rows_link_a_runtime_call_to_its_operator():
    # Chrome-trace events as torch's export writes them (microseconds; a runtime call carries its operator's
    # "External id" and its kernel's "correlation"): the rows split as test_split_trace_keeps_the_steps_threads's do.
    # Metadata and flow events, and events without a category, are not rows.
    main, loader = 11, 13
    events = [{"ph": "M", "name": "thread_name", "pid": 1, "tid": main, "args": {"name": "python"}},
              {"ph": "X", "cat": "user_annotation", "name": ITERATION, "ts": 1000.0, "dur": 0.1, "tid": main,
               "args": {"External id": 1}},
              {"ph": "X", "cat": "cpu_op", "name": "aten::mul", "ts": 1000.01, "dur": 0.01, "tid": main,
               "args": {"External id": 4}},
              {"ph": "X", "cat": "cpu_op", "name": "aten::copy_", "ts": 1000.05, "dur": 0.01, "tid": loader,
               "args": {"External id": 6}},
              {"ph": "X", "cat": "cuda_runtime", "name": "cudaStreamSynchronize", "ts": 1000.012, "dur": 0.006,
               "tid": main, "args": {"External id": 4, "correlation": 7}},
              {"ph": "X", "cat": "cuda_runtime", "name": "cudaStreamSynchronize", "ts": 1000.052, "dur": 0.006,
               "tid": loader, "args": {"External id": 6, "correlation": 8}},
              {"ph": "X", "cat": "kernel", "name": "triton_poi_fused_0", "ts": 1000.015, "dur": 0.01, "pid": 0,
               "tid": 7, "args": {"External id": 4, "correlation": 7}},
              {"ph": "s", "cat": "ac2g", "name": "launch", "ts": 1000.012, "id": 7, "tid": main},
              {"ph": "X", "name": "no category", "ts": 1000.0, "dur": 1.0, "tid": main}]
    rows = chrome_trace_rows(events)
    assert [r.activity for r in rows] == ["user_annotation", "cpu_op", "cpu_op", "cuda_runtime", "cuda_runtime",
                                          "kernel"]
    assert rows[3] == Row("cuda_runtime", "cudaStreamSynchronize", 1000012, 1000018, main, 7, 4)
    trace = split_trace(rows)
    assert trace.windows == [(1000000, 1000100)]
    assert trace.host_ops == [(1000010, 1000020)]
    assert trace.waits == [(1000012, 1000018)]  # the loader's wait is not the step's
    assert trace.kernels == [(1000015, 1000025, "triton_poi_fused_0")]


def test_chrome_trace_rows_give_a_kernel_its_launchs_correlation():
    # A kernel's event carries its operator's "External id" and its launch's "correlation": its row's correlation is
    # the latter (as the launch's row's, runtime or driver call alike), its link the former.
    main = 11
    events = [{"ph": "X", "cat": "cpu_op", "name": "aten::mul", "ts": 10.0, "dur": 1.0, "tid": main,
               "args": {"External id": 4}},
              {"ph": "X", "cat": "cuda_driver", "name": "cuLaunchKernel", "ts": 10.2, "dur": 0.1, "tid": main,
               "args": {"External id": 4, "correlation": 9}},
              {"ph": "X", "cat": "kernel", "name": "triton_poi_fused_0", "ts": 10.5, "dur": 2.0, "pid": 0, "tid": 7,
               "args": {"External id": 4, "correlation": 9}}]
    rows = chrome_trace_rows(events)
    assert rows[1] == Row("cuda_driver", "cuLaunchKernel", 10200, 10300, main, 9, 4)
    assert rows[2] == Row("kernel", "triton_poi_fused_0", 10500, 12500, 7, 9, 4)
    events[0]["args"]["External id"] = 9  # an operator whose External id equals the kernel's correlation
    events[1]["args"]["External id"] = events[2]["args"]["External id"] = 9
    rows = chrome_trace_rows(events + [{"ph": "X", "cat": "user_annotation", "name": ITERATION, "ts": 9.0,
                                        "dur": 5.0, "tid": main, "args": {"External id": 1}},
                                       {"ph": "X", "cat": "user_annotation", "name": PHASE + "loss", "ts": 10.0,
                                        "dur": 0.25, "tid": main, "args": {"External id": 2}}])
    assert summarise_phases(split_trace(rows))["loss"]["launches"] == 1


PHASES = ("sample", "model", "render", "loss", "backward", "step")


def _phase_rows(rng: random.Random, iterations: list[tuple[int, int]], main: int) -> list[Row]:
    """Each iteration cut into consecutive phases (a name may come back, as `render` and `loss` do per view), gaps
    left unannotated, and a `model.decoders` nested in each `model`."""
    rows = []
    for lo, hi in iterations:
        cuts = sorted(rng.sample(range(lo, hi + 1), min(hi + 1 - lo, rng.randrange(2, 9))))
        for start, end in zip(cuts, cuts[1:]):
            if rng.random() < 0.2:
                continue
            name = rng.choice(PHASES)
            rows.append(Row("user_annotation", PHASE + name, start, end, main, 0, 0))
            if name == "model":
                a, b = sorted(rng.randrange(start, end + 1) for _ in range(2))
                rows.append(Row("user_annotation", PHASE + "model.decoders", a, b, main, 0, 0))
    return rows


@pytest.mark.parametrize("seed", range(20))
def test_phases_against_cell_count(seed):
    # Synthetic trace: iterations on the main thread, phase windows (nested, repeated), kernels launched from the
    # main, the autograd and the loader's threads (the runtime call linked to its thread's operator, or carrying its
    # own thread), some launched twice (runtime and driver), overlapping on two streams, one launched before every
    # phase, one with no launch; blocking waits on the main and the loader's threads; a phase-named annotation on the
    # loader's thread. Brute force per phase on the grid's cells: the windows' cells, the kernels whose earliest launch
    # from a step thread lies in one of them, their lengths' sum and cells, the main thread's waits inside the windows.
    rng = random.Random(seed)
    main, autograd, loader = 11, 12, 13
    step = (main, autograd)
    operator = {main: 1, autograd: 2, loader: 3}
    cuts = sorted(rng.sample(range(30, SPAN - 30), rng.randrange(1, 4)))
    iterations = list(zip([10] + cuts, cuts + [SPAN - 10]))
    rows = [Row("user_annotation", ITERATION, lo, hi, main, 5, 0) for lo, hi in iterations]
    rows += [Row("cpu_op", "aten::mul", 0, SPAN, main, 1, 0),
             Row("cpu_op", BACKWARD_OP + ": MulBackward0", 0, SPAN, autograd, 2, 0),
             Row("cpu_op", "aten::copy_", 0, SPAN, loader, 3, 0),
             Row("user_annotation", PHASE + "loss", 0, SPAN, loader, 6, 0)]  # not the main thread's
    rows += _phase_rows(rng, iterations, main)
    names = ["ncclDevKernel_AllReduce_Sum_f32_RING_LL", "triton_poi_fused_0", "rasterize_to_pixels_fwd"]
    kernels = []  # (launch, thread, start, end, name)
    for k in range(rng.randrange(0, 60)):
        correlation = 1000 + k
        launch, thread = (2, main) if k == 0 else (rng.randrange(SPAN - 40), rng.choice(list(operator)))
        linked = rng.random() < 0.5  # the profiler's own thread number, resolved through the operator
        rows.append(Row(rng.choice(["cuda_runtime", "cuda_driver"]), "cudaLaunchKernel", launch, launch + 1,
                        99 if linked else thread, correlation, operator[thread] if linked else 0))
        if rng.random() < 0.2:
            rows.append(Row("cuda_driver", "cuLaunchKernel", launch + 3, launch + 4, thread, correlation, 0))
        start = launch + rng.randrange(0, 20)
        end = start + rng.randrange(0, 20)
        name = rng.choice(names)
        rows.append(Row("kernel", name, start, end, rng.choice([7, 8]), correlation, operator[thread]))
        kernels.append((launch, thread, start, end, name))
    rows.append(Row("kernel", "orphan", 50, 60, 7, 5000, 0))  # no launch recorded: in no phase
    waits = {thread: _intervals(rng, rng.randrange(0, 6)) for thread in (main, loader)}
    rows += [Row("cuda_runtime", "cudaStreamSynchronize", s, e, 99, 0, operator[thread])
             for thread, spans in waits.items() for s, e in spans]
    rng.shuffle(rows)

    trace = split_trace(rows)
    got = summarise_phases(trace)
    assert summarise(trace)["phases"] == got
    windows: dict[str, list] = {}
    for r in rows:
        if r.activity == "user_annotation" and r.name.startswith(PHASE) and r.thread == main:
            windows.setdefault(r.name[len(PHASE):], []).append((r.start, r.end))
    assert list(got) == sorted(windows, key=lambda name: (min(s for s, _ in windows[name]), name))  # step order
    n = len(iterations)
    for name, spans in windows.items():
        cells = _cells(spans)
        mine = [(s, e, k) for t, thread, s, e, k in kernels if thread in step and cells[t]]
        expect = {"host_ms": cells.sum(), "host_wait_ms": (cells & _cells(waits[main])).sum(),
                  "launches": len(mine), "kernel_ms": sum(e - s for s, e, _ in mine),
                  "gpu_busy_ms": _cells([(s, e) for s, e, _ in mine]).sum(),
                  "nccl_ms": _cells([(s, e) for s, e, k in mine if k.startswith("nccl")]).sum()}
        for key, value in expect.items():
            assert got[name][key] == pytest.approx(value / n * (1 if key == "launches" else 1e-6), abs=1e-12), \
                (name, key)


def test_phase_verdict_thresholds():
    def phase(host, busy, wait=0.0):
        return {"host_ms": host, "gpu_busy_ms": busy, "host_wait_ms": wait}

    assert [phase_verdict(phase(10.0, busy)) for busy in (0.0, 4.9, 5.0, 7.4, 7.5, 30.0)] == \
        ["host", "host", "mixed", "mixed", "GPU", "GPU"]
    assert phase_verdict(phase(10.0, 0.0, wait=5.0)) == "wait" and phase_verdict(phase(10.0, 0.0, 4.9)) == "host"
    assert phase_verdict(phase(0.0, 1.0)) == "-"


def test_a_real_cpu_trace_reads_as_its_iterations():
    # The profiler's exported rows (trace_rows) of 3 annotated iterations of a forward and backward on the CPU: three
    # windows, the operators inside them (autograd's among them), no kernel.
    weight = torch.randn(64, 64, requires_grad=True)
    profiler = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
    profiler.start()
    for _ in range(3):
        with torch.profiler.record_function(ITERATION):
            (weight @ weight).square().sum().backward()
    profiler.stop()
    rows = trace_rows(profiler)
    trace = split_trace(rows)
    summary = summarise(trace)
    assert len(trace.windows) == 3 and not trace.kernels
    assert any(name.startswith("autograd::engine") for name in (r.name for r in rows if r.activity == "cpu_op"))
    assert 0 < summary["host_ms"] <= summary["wall_ms"]
    assert summary["gpu_busy_ms"] == 0 and summary["kernels"] == 0 and summary["gpu_idle"] == 1


def test_bus_bandwidth_is_nccl_tests_definition():
    # 1 GB all-reduced in 10 ms on 4 ranks: 100 GB/s algorithm bandwidth, x 2 (4 - 1) / 4 on the bus.
    assert bus_bandwidth_gbs(1e9, 10.0, 4) == pytest.approx(150.0)
    assert bus_bandwidth_gbs(1e9, 10.0, 1) == 0.0


def _no_sync() -> None:
    pass


def _no_bytes() -> int:
    return 0


def test_a_trace_that_cannot_be_read_loses_the_kernel_profile_only(tmp_path, capsys):
    # A trace that cannot be read (a torch whose export differs): the rank's record (ms/it,
    # phases, graphs) must still be written, with no kernel profile, and the reason said.
    probe = fit_multi_gpu.RankProbe(str(tmp_path), 1, 3, 1, 0, kernels=2, synchronize=_no_sync, peak_bytes=_no_bytes)
    with mock.patch.object(fit_multi_gpu, "trace_rows", side_effect=AttributeError("no activity_type")):
        for iteration in range(7):
            probe(iteration)
    record = json.loads((tmp_path / "rank0.json").read_text())
    assert record["kernels"] is None and record["ms"] >= 0 and "phases_ms" in record
    assert "kernel profile not read (AttributeError: no activity_type)" in capsys.readouterr().err


def test_phases_are_annotated_in_the_profiled_iterations_only(tmp_path):
    # The probe's phase(name) over a fit's iterations (the fit calls on_iteration(i) after iteration i, 1-based):
    # the timer's synchronised phase in iterations 3..4, a profiler annotation PHASE + name in 5..6 (never both),
    # nothing before or after; the profiled iterations' trace holds the phases' windows.
    probe = fit_multi_gpu.RankProbe(str(tmp_path), 1, 3, 2, 0, kernels=2, synchronize=_no_sync, peak_bytes=_no_bytes)
    timed, annotated = [], []
    for iteration in range(8):  # the iteration begun after on_iteration(iteration)
        if iteration:
            probe(iteration)
        with probe.phase("loss") as entered:
            if isinstance(entered, torch.profiler.record_function):
                assert entered.name == PHASE + "loss"
                annotated.append(iteration)
            if probe.timer.active:
                timed.append(iteration)
            torch.ones(4).sum()
    assert timed == [3, 4] and annotated == [5, 6]
    record = json.loads((tmp_path / "rank0.json").read_text())
    assert set(record["kernels"]["phases"]) == {"loss"} and record["phases_ms"].keys() == {"loss"}


def _cpu_probe_hooks(folder: str, rank: int):
    """The benchmark's hooks of a rank (fit_multi_gpu.rank_hooks) on the CPU: 1 warm-up iteration, 2 timed, 1 timed
    per phase, 2 under the profiler (iterations 5 and 6; the 7th ends the fit with its evaluation)."""
    from pig.avatar.parallel_fit import RankHooks

    probe = fit_multi_gpu.RankProbe(folder, 1, 3, 1, rank, kernels=2, synchronize=_no_sync, peak_bytes=_no_bytes)
    return RankHooks(on_iteration=probe, phase=probe.phase, on_reducer=probe.reducer)


def test_rank_records_of_a_profiled_data_parallel_fit(small_capture, tmp_path, capsys):
    # The benchmark's rank hooks in a 2-process gloo fit: each rank's record holds its kernel profile (2 iterations,
    # no kernel on the CPU, the host's operators inside the wall time) and the gradient all-reduce's buckets, the
    # same on both ranks and holding every trainable parameter; `--collect` prints them.
    from pig.avatar.checkpoint import load_avatar
    from pig.avatar.parallel_fit import fit_parallel
    from preset_files import write_test_preset

    run = tmp_path / "work" / "scaling_2gpu"
    run.mkdir(parents=True)
    preset = write_test_preset(tmp_path, iterations=7, eval_every=10**6)
    fit_parallel(small_capture, run / "fit", preset, "pig", 2, "cpu", progress_s=1e6, timeout_s=120,
                 rank_hooks=functools.partial(_cpu_probe_hooks, str(run)))
    records = [json.loads((run / f"rank{rank}.json").read_text()) for rank in range(2)]
    for record in records:
        profile = record["kernels"]
        assert profile["iterations"] == 2 and profile["kernels"] == 0 and profile["gpu_busy_ms"] == 0
        assert 0 < profile["host_ms"] <= profile["wall_ms"]
        assert set(record["phases_ms"]) >= {"model", "loss", "backward", "reduce", "step"}
        phases = profile["phases"]  # the same phases' windows in the profiled iterations, no kernel in any
        assert set(phases) >= {"sample", "model", "render", "loss", "backward", "reduce", "step"}
        assert all(p["launches"] == p["kernel_ms"] == p["gpu_busy_ms"] == 0 for p in phases.values())
        assert all(phases[n]["host_ms"] > 0 for n in ("model", "render", "loss", "backward", "step"))
        assert sum(p["host_ms"] for n, p in phases.items() if "." not in n) <= profile["wall_ms"]
    assert records[0]["bucket_bytes"] == records[1]["bucket_bytes"]
    model = load_avatar(run / "fit" / "avatar.pt")  # the avatar rebuilt: its trainable parameters' bytes
    assert sum(records[0]["bucket_bytes"]) == sum(p.numel() * p.element_size() for p in model.parameters()
                                                  if p.requires_grad)
    (run / "run.json").write_text(json.dumps({"gpus": 2, "sharded": False, "name": run.name}))
    assert fit_multi_gpu.main(["--collect", "--workdir", str(run.parent)]) == 0
    out = capsys.readouterr().out
    assert "| 2 GPU | 0 |" in out and "| 2 GPU | 1 |" in out
    assert "GPU idle per rank (1 - busy / wall): 2 GPU: 100 % / 100 %" in out
    by_phase = [line for line in out.splitlines() if line.startswith(("| backward |", "| loss |"))
                and line.count("|") == 11]  # the kernel profile's by phase, not the synchronised phases' table
    assert [line.split("|")[1:3] for line in by_phase] == [[" loss ", " 0 "], [" loss ", " 1 "],  # in step order
                                                           [" backward ", " 0 "], [" backward ", " 1 "]]
    assert all(line.endswith("| 0 % | host |") for line in by_phase)  # no kernel: the host's alone


def _kernel_summary(wall: float, busy: float) -> dict:
    return {"wall_ms": wall, "gpu_busy_ms": busy, "nccl_ms": 1.0, "compute_ms": busy - 0.5, "nccl_alone_ms": 0.5,
            "all_reduce_ms": 0.8, "host_ms": wall - 1, "host_wait_ms": 0.2, "kernels": 1234.0, "iterations": 5,
            "gpu_idle": 1 - busy / wall, "top_kernels": [["triton_poi_fused_0", 3.0, 10.0]]}


def _write_run(folder: Path, gpus: int, sharded: bool, ranks: int) -> None:
    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps({"gpus": gpus, "sharded": sharded, "name": folder.name, "fit_s": 1.0,
                                                 "heldout_psnr": 20.0, "train_s": 1.0, "iterations": 130}))
    for rank in range(ranks):
        (folder / f"rank{rank}.json").write_text(json.dumps({
            "rank": rank, "ms": 100.0 / gpus, "peak_gib": 1.0, "phases_ms": {"backward": 40.0 / gpus},
            "graphs": [9, 0, 0], "graph_breaks": 0, "kernels": _kernel_summary(100.0 / gpus, 30.0 / gpus),
            "bucket_bytes": None if gpus == 1 else [2**20, 3 * 2**20]}))


def test_collect_prints_every_run_found_and_names_the_partial_ones(small_capture, tmp_path, capsys):
    work = tmp_path / "work"
    shutil.copytree(small_capture, work / fit_multi_gpu.CAPTURE)
    _write_run(work / "scaling_1gpu", 1, False, 1)
    _write_run(work / "scaling_4gpu_sharded", 4, True, 4)
    _write_run(work / "scaling_2gpu_sharded", 2, True, 1)  # rank 1 never wrote its record
    (work / "scaling_2gpu").mkdir()  # started, nothing written
    assert fit_multi_gpu.main(["--collect", "--workdir", str(work), "--cameras", "99"]) == 0
    out, err = capsys.readouterr()
    assert "scaling_2gpu: no run.json" in err and "scaling_2gpu_sharded/rank1.json: missing" in err
    rows = [line for line in out.splitlines() if line.startswith(("| 1 |", "| 4 |", "| 2 |"))]
    assert [row.split("|")[1:3] for row in rows] == [[" 1 ", " one process "], [" 4 ", " sharded "]]
    assert "| 4.00x |" in rows[1] and "| 4.0 | 2 |" in rows[1]  # speed-up; 4 MiB all-reduced in 2 buckets
    cameras = json.loads((small_capture / "cameras.json").read_text())
    frames = len(np.load(small_capture / "smplx.npz")["frames"])
    assert f"capture {len(cameras)} cameras x {frames} frames" in out  # the capture on disk, not --cameras 99
    profile = [line for line in out.splitlines() if line.startswith("| 4 GPU sharded |")]
    assert len(profile) == 4 + 4  # the solve-phase table's rows and the kernel profile's, per rank
    assert "GPU idle per rank (1 - busy / wall): 1 GPU: 70 %; 4 GPU sharded: 70 % / 70 % / 70 % / 70 %" in out


def test_collect_without_any_finished_run_says_so(tmp_path, capsys):
    (tmp_path / "scaling_1gpu").mkdir()
    assert fit_multi_gpu.main(["--collect", "--workdir", str(tmp_path)]) == 1
    assert "no finished scaling run" in capsys.readouterr().err
    assert fit_multi_gpu.main(["--collect", "--workdir", str(tmp_path / "none")]) == 1
    assert "no scaling run folder" in capsys.readouterr().err


def test_parity_verdict_against_welch_by_hand():
    # means 2 and 3; sample variances 2 and 2; standard error sqrt(2/2 + 2/2) = sqrt(2); 3 is the range's top
    assert fit_multi_gpu.parity_verdict([1.0, 3.0], [2.0, 4.0]) == (
        "difference of means +1.000 dB, mean inside the 1-GPU range, standard error 1.414 dB (0.71 of them): "
        "parity holds")
    # means 1.1 and 1.5, above the range [1.0, 1.2]: not parity, though only 0.78 standard errors away
    assert fit_multi_gpu.parity_verdict([1.0, 1.2], [1.0, 2.0]) == (
        "difference of means +0.400 dB, mean outside the 1-GPU range, standard error 0.510 dB (0.78 of them): "
        "parity not shown")
    # inside the range [1, 2] but 7.1 standard errors away: mean 10/9, variance 1/9 over 9 runs, so the error 1/9
    reference = [1.0] * 8 + [2.0]
    assert fit_multi_gpu.parity_verdict(reference, [1.9, 1.9, 1.9]) == (
        "difference of means +0.789 dB, mean inside the 1-GPU range, standard error 0.111 dB (7.10 of them): "
        "parity not shown")
    assert fit_multi_gpu.parity_verdict([28.0], [28.0, 28.1]).endswith("parity not decided")


def test_systematic_verdict_of_the_step_after_step_comparison():
    import parity_trajectory

    reference = {1: 1.0, 50: 1.0, 100: 1.0, 200: 1.0, 300: 1.0}
    rerun = {i: 1.0 + 1e-5 for i in reference}
    # a term dropped: the first step 2e-4 off
    assert parity_trajectory.systematic_verdict(reference, rerun, {**rerun, 1: 1.0 + 2e-4}).startswith(
        "systematic: the first step's loss off by 2.0e-04")
    # rounding at first, then 20x the rerun's distance at every checkpoint
    far = {1: 1.0, **{i: 1.0 + 2e-4 for i in (50, 100, 200, 300)}}
    assert parity_trajectory.systematic_verdict(reference, rerun, far).startswith("systematic: more than 10x")
    # 20x at three checkpoints, 5x at one: rounding only, each ratio listed
    assert parity_trajectory.systematic_verdict(reference, rerun, {**far, 200: 1.0 + 5e-5}) == (
        "rounding only: first step off by 0.0e+00; against the rounding-only run 50: 20x, 100: 20x, 200: 5x, 300: 20x")
    # a rounding-only run equal to the reference bit for bit: a difference above the floor counts as infinitely
    # farther, one below it (1e-7, rounding on the CPU) does not
    same = dict(reference)
    assert parity_trajectory.systematic_verdict(reference, same, far).startswith("systematic: more than 10x")
    assert parity_trajectory.systematic_verdict(reference, same, {i: 1.0 + 1e-7 for i in reference}).startswith(
        "rounding only")
    # a fit shorter than every checkpoint is judged on its first step alone
    assert parity_trajectory.systematic_verdict({1: 1.0, 20: 1.0}, {1: 1.0, 20: 1.0}, {1: 1.0, 20: 1.1}) == (
        "rounding only: first step off by 0.0e+00; against the rounding-only run -")
