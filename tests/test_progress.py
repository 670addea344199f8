"""Progress bars in rule logs: at most one update every 30 s when the bar does not write to a terminal."""
import io
import subprocess
import sys

import tqdm.std

from pig.progress import LOG_INTERVAL_S, progress_bar


class Terminal(io.StringIO):
    def isatty(self):
        return True


class Clock:
    """Stands in for tqdm's clock: advanced by hand, so a 100 s loop takes no time."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


def draw_times(stream, steps, seconds_per_step, monkeypatch, **kwargs):
    """Simulated times at which a bar over `steps` items, each taking `seconds_per_step`, wrote to `stream`."""
    clock = Clock()
    monkeypatch.setattr(tqdm.std, "time", clock)
    written = []
    write = stream.write

    def record(text):
        if "\r" in text:
            written.append(clock.now)
        return write(text)

    monkeypatch.setattr(stream, "write", record)
    for _ in progress_bar(range(steps), file=stream, **kwargs):
        clock.now += seconds_per_step
    return written


def test_log_file_gets_an_update_at_most_every_30_s(monkeypatch):
    times = draw_times(io.StringIO(), 2000, 0.1, monkeypatch)  # 200 s of work
    gaps = [b - a for a, b in zip(times[:-1], times[1:-1])]  # the last draw is the bar's close, whenever it ends
    assert 200 / LOG_INTERVAL_S - 1 <= len(times) <= 200 / LOG_INTERVAL_S + 3, times
    assert min(gaps) >= LOG_INTERVAL_S, gaps


def test_terminal_keeps_tqdm_rate(monkeypatch):
    times = draw_times(Terminal(), 2000, 0.1, monkeypatch)
    assert len(times) > 100  # tqdm's default: ten a second


def test_caller_interval_wins(monkeypatch):
    times = draw_times(io.StringIO(), 100, 1.0, monkeypatch, mininterval=5)
    gaps = [b - a for a, b in zip(times[:-1], times[1:-1])]
    assert min(gaps) >= 5 and len(times) >= 100 / 5 - 1


def test_monitor_thread_waits_for_the_interval():
    """tqdm's monitor redraws a bar idle for `maxinterval` (10 s by default): raised for logs too."""
    bar = progress_bar(total=10, file=io.StringIO())
    assert bar.maxinterval >= LOG_INTERVAL_S and bar.mininterval == LOG_INTERVAL_S
    bar.close()
    bar = progress_bar(total=10, file=Terminal())
    assert bar.mininterval < 1
    bar.close()


def test_default_stream_is_stderr(tmp_path):
    """A stage's bar writes to stderr; redirected to a log (as every rule does) it takes the 30 s interval."""
    code = "from pig.progress import progress_bar; print(progress_bar(total=1).mininterval)"
    with open(tmp_path / "rule.log", "w") as log:
        out = subprocess.run([sys.executable, "-c", code], stderr=log, stdout=subprocess.PIPE, text=True, check=True)
    assert float(out.stdout) == LOG_INTERVAL_S
