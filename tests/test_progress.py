"""Progress reports: tqdm on a terminal, a few plain lines in a log (fake stream, fake clock)."""

from __future__ import annotations

import io
import re

import tqdm

from mvpose_jax.progress import LineProgress, progress_bar


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class TerminalStream(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_terminal_gets_a_tqdm_bar():
    stream = TerminalStream()
    bar = progress_bar(total=3, desc="work", unit="frame", file=stream)
    assert isinstance(bar, tqdm.tqdm)
    bar.update(3)
    bar.close()
    assert "\r" in stream.getvalue()  # tqdm's redraws, as before


def test_a_log_gets_one_line_per_interval_and_one_at_the_end():
    stream, clock = io.StringIO(), FakeClock()
    bar = progress_bar(
        total=390, desc="pipeline", unit="frame", file=stream, interval_s=10.0, clock=clock
    )
    assert isinstance(bar, LineProgress)
    # 390 updates over 48.75 s of fake time, one every 1/8 s (exact in binary): lines at 10, 20,
    # 30 and 40 s, and the final one.
    for _ in range(390):
        clock.now += 0.125
        bar.update(1)
    bar.close()
    bar.close()  # a second close writes nothing
    text = stream.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert len(lines) == 5
    # 10 s at 8 frames/s: 80 of 390 done, 310 / 8 = 38.75 s left.
    assert lines[0] == "pipeline: 80/390 frame (21%), 8 frame/s, 0:10 elapsed, 0:39 left"
    assert lines[3].startswith("pipeline: 320/390 frame (82%), 8 frame/s, 0:40 elapsed")
    assert lines[-1] == "pipeline: 390/390 frame (100%), 8 frame/s, 0:49 elapsed, 0:00 left"


def test_close_repeats_no_line_already_written():
    stream, clock = io.StringIO(), FakeClock()
    bar = progress_bar(total=2, unit="step", file=stream, clock=clock, interval_s=1)
    clock.now += 1
    bar.update(2)
    bar.close()
    assert stream.getvalue().splitlines() == ["2/2 step (100%), 2 step/s, 0:01 elapsed, 0:00 left"]


def test_lines_without_a_total_show_count_and_rate_only():
    stream, clock = io.StringIO(), FakeClock()
    with progress_bar(desc="read", unit="chunk", file=stream, clock=clock, interval_s=5) as bar:
        clock.now += 4
        bar.update(8)  # before the interval: no line
        assert stream.getvalue() == ""
        clock.now += 4
        bar.update(8)
        bar.set_postfix(loss="0.25", best=0.2)
    lines = stream.getvalue().splitlines()
    assert lines == [
        "read: 16 chunk, 2 chunk/s, 0:08 elapsed",
        "read: 16 chunk, 2 chunk/s, 0:08 elapsed, loss=0.25, best=0.2",
    ]


def test_wrapping_an_iterable_counts_its_items_and_resumes_from_initial():
    stream, clock = io.StringIO(), FakeClock()
    items = []
    for x in progress_bar(range(4), desc="export", unit="file", file=stream, clock=clock):
        clock.now += 1
        items.append(x)
    assert items == [0, 1, 2, 3]
    assert stream.getvalue().splitlines() == [
        "export: 4/4 file (100%), 1 file/s, 0:04 elapsed, 0:00 left"
    ]

    stream = io.StringIO()
    bar = progress_bar(total=10, unit="step", file=stream, clock=clock, initial=6)
    clock.now += 2
    bar.update(2)  # resumed at 6: the rate counts this run's 2 steps only
    bar.close()
    assert re.fullmatch(
        r"8/10 step \(80%\), 1 step/s, 0:02 elapsed, 0:02 left\n", stream.getvalue()
    )


def test_disabled_reports_nothing_but_still_iterates():
    stream = io.StringIO()
    assert list(progress_bar([1, 2], disable=True, file=stream)) == [1, 2]
    assert stream.getvalue() == ""


def test_a_smoke_sized_job_stays_a_few_lines():
    # 20 000 updates in 156.25 s of fake time (1/128 s each): 15 interval lines and the final one.
    stream, clock = io.StringIO(), FakeClock()
    with progress_bar(total=20_000, unit="frame", file=stream, clock=clock) as bar:
        for _ in range(20_000):
            clock.now += 1 / 128
            bar.update()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 16
    assert lines[-1] == "20000/20000 frame (100%), 128 frame/s, 2:36 elapsed, 0:00 left"


def test_fast_rates_are_plain_numbers():
    stream, clock = io.StringIO(), FakeClock()
    bar = progress_bar(total=3040, unit="frame", file=stream, clock=clock)
    clock.now += 2
    bar.update(3040)
    bar.close()
    assert "1520 frame/s" in stream.getvalue()
