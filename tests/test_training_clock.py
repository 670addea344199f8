"""A fit's training seconds (pig.avatar.training_clock): equal time means equal training, so compilation,
held-out evaluations and checkpoint writes stay outside `fit.time_budget_s` for every variant alike."""
import math

import pandas as pd
import pytest
import torch

from pig import cuda_graphs
from pig.avatar.training_clock import TrainingClock, compile_events
from preset_files import write_test_preset


class FakeClock:
    """Seconds that pass only when a test says so."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


def test_clock_leaves_out_compiling_steps_evaluations_and_checkpoints():
    clock, events = FakeClock(), [0]
    timer = TrainingClock(wall_before=7.0, train_before=5.0, clock=clock, events=lambda: events[0])
    with timer.iteration():  # a plain step: training
        clock.advance(2.0)
    with timer.iteration():  # a step that compiles: all of it is compilation
        clock.advance(30.0)
        events[0] += 3
    with timer.excluding("evaluation"):
        clock.advance(4.0)
    with timer.excluding("checkpoint"):
        clock.advance(0.5)
    clock.advance(1.0)  # between steps (logging, sampling): training
    assert timer.wall() == 7.0 + 37.5
    assert timer.training() == 5.0 + 3.0
    assert dict(timer.excluded) == {"compilation": 30.0, "evaluation": 4.0, "checkpoint": 0.5}
    with pytest.raises(AssertionError):
        with timer.excluding("coffee"):
            pass


def test_compile_events_grow_with_a_graph_capture_and_a_compiled_function():
    before = compile_events()
    cuda_graphs.captures += 1  # what pig.cuda_graphs.capture counts (CUDA only)
    assert compile_events() == before + 1
    compiled = torch.compile(lambda x: x * 2 + 1, backend="eager")  # Dynamo's tracing, no C++ toolchain needed
    middle = compile_events()
    compiled(torch.ones(3))
    after = compile_events()
    compiled(torch.ones(3))  # cached: nothing compiles
    assert after > middle and compile_events() == after


@pytest.mark.slow
def test_a_time_budget_counts_training_only_for_a_variant_that_is_not_pig(small_capture, tmp_path, monkeypatch):
    """`no_precond` under a 5.5 s budget where each step trains 1 s: its third step also compiles for 100 s and counts
    whole as compilation, each held-out evaluation takes 50 s; it stops after 7 steps with 6 training seconds (on
    wall time it would stop after 3), the log says how much compilation it held, and the learning-rate schedule's
    time fraction is that of training seconds."""
    import pig.avatar.training as training

    clock = FakeClock()
    steps = []
    plain_loss = training.iteration_loss

    def loss_that_compiles_once(*args, **kwargs):
        steps.append(len(steps) + 1)
        clock.advance(1.0)
        if len(steps) == 3:  # the first call of a graph: compilation inside the step
            cuda_graphs.captures += 1
            clock.advance(100.0)
        return plain_loss(*args, **kwargs)

    plain_psnr = training.HeldOut.psnr

    def slow_psnr(self, *args, **kwargs):
        clock.advance(50.0)
        return plain_psnr(self, *args, **kwargs)

    fractions = []
    plain_at = training.LossTerms.at

    def recorded_at(self, iteration, done):  # also called once as the loss is built
        fractions.append(done)
        return plain_at(self, iteration, done)

    monkeypatch.setattr(training, "iteration_loss", loss_that_compiles_once)
    monkeypatch.setattr(training.HeldOut, "psnr", slow_psnr)
    monkeypatch.setattr(training.LossTerms, "at", recorded_at)
    preset = write_test_preset(tmp_path, iterations=1000, eval_every=2, log_every=1, time_budget_s=5.5,
                               checkpoint_minutes=1e6)
    training.fit(small_capture, tmp_path / "fit", preset, variant="no_precond", clock=clock)
    log = pd.read_csv(tmp_path / "fit" / "train_log.csv")
    assert steps == [1, 2, 3, 4, 5, 6, 7]
    last = log.iloc[-1]
    assert last["iteration"] == 7 and last["train_s"] == 6.0 and last["compile_s"] == 101.0
    assert log["heldout_psnr"].notna().sum() == 5  # at the start (before the clock), 2, 4, 6 and the end
    assert last["wall_s"] == 7.0 + 100.0 + 50.0 * 3  # the end's evaluation comes after its row
    trained_before = [0, 1, 2, 2, 3, 4, 5]  # the third step's second is compilation
    assert all(math.isclose(f, t / 5.5) for f, t in zip(fractions[1:], trained_before, strict=True)), fractions
    assert torch.load(tmp_path / "fit" / "avatar.pt", weights_only=True)["spec"]["variant"] == "no_precond"
