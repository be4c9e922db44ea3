"""rigctl.progress: a redrawn bar on a terminal, plain lines otherwise (issue 9)."""
from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import pytest

from rigctl.config.config import load_config, resolve_config_path
from rigctl.devices import TableState
from rigctl.engine.estimate import estimate
from rigctl.engine.procedure import load_procedure
from rigctl.progress import CounterGaps, NullProgress, Progress, WorkProgress, make_progress
from helpers import ROOT


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


class Wall:
    """A wall clock the test advances."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Seg:
    first_sample: int
    last_sample: int


@pytest.fixture(scope="module")
def plan():
    cfg = load_config(resolve_config_path(None))
    proc = load_procedure(str(ROOT / "procedures" / "24pos.yaml"),
                          {"warmup": "1 min", "sample": "5 s"}, cfg.limits)
    return estimate(proc.steps, cfg)


def screen(text: str) -> list[str]:
    """What a terminal shows: per line, the text after the last carriage return."""
    out = []
    for chunk in text.split("\n"):
        parts = [x.replace("\x1b[K", "") for x in chunk.split("\r")]
        parts = [x for x in parts if x]
        if parts:
            out.append(parts[-1])
    return out


def _state(t: float, deg=(0.0, 90.0, 45.0), dps=(0.0, 0.0, 40.0)) -> TableState:
    return TableState(t, np.radians(deg), np.radians(dps), (0, 0, 0))


def drive(p: Progress, plan, wall: Wall, n_steps: int = 3, poll_s: float = 0.5,
          wall_per_poll: float = 0.05, rate_hz: float = 100.0, drop_every: int = 0) -> None:
    """Run the first n_steps of the plan through p, rig time = estimate of each step."""
    p.start(plan, "24pos")
    t, n, dropped, k = 0.0, 0, 0, 0
    for e in [e for e in plan if e.step.is_motion][:n_steps]:
        p.step_started(e.step)
        first = n
        for _ in range(int(round(e.total_s / poll_s))):
            t += poll_s
            n += int(rate_hz * poll_s)
            k += 1
            if drop_every and k % drop_every == 0:
                dropped += 1
            wall.t += wall_per_poll
            p.update(t, _state(t), n, dropped)
        p.step_finished(e.step, Seg(first, n))
    p.finish("complete")


def test_tty_redraws_one_line_throttled_to_5_hz(plan) -> None:
    out, wall = FakeTTY(), Wall()
    p = Progress(out, wall=wall, width=400)  # tty detected from isatty()
    assert p.tty
    drive(p, plan, wall)
    text = out.getvalue()
    redraws = text.count("\r") - text.count("\r\x1b[K")  # bar draws, not line clears
    polls = sum(int(round(e.total_s / 0.5)) for e in [e for e in plan if e.step.is_motion][:3])
    wall_s = polls * 0.05
    # at most 5 redraws per wall second (+ forced ones at the 3 step starts and 3 messages)
    assert redraws <= 5 * wall_s + 1 + 6
    assert redraws >= 5 * wall_s * 0.8  # ... but it does keep updating
    # updates never print a newline: the screen shows the plan, the 3 step ends and finish
    lines = screen(text)
    assert len(lines) == 5, lines
    assert [ln.split(" ", 1)[0] for ln in lines[1:4]] == ["[1/25]", "[2/25]", "[3/25]"]
    assert all(" done: " in ln for ln in lines[1:4])
    assert "[1/25]" in text and "[3/25]" in text and "#" in text
    assert "IMU 100.0 Hz" in text and "deg/s" in text and "90.0" in text
    assert lines[-1].startswith("complete: 3/25 steps")


def test_tty_bar_percentage_and_remaining_time_advance(plan) -> None:
    out, wall = FakeTTY(), Wall()
    p = Progress(out, wall=wall, width=400, redraw_hz=1000)
    motion = [e for e in plan if e.step.is_motion]
    p.start(plan)
    total = sum(e.total_s for e in motion)
    p.update(0.0, _state(0.0), 0, 0)
    p.step_started(motion[0].step)
    assert p.remaining_s() == pytest.approx(total)
    wall.t += 1.0
    p.update(motion[0].total_s / 2, _state(1.0), 100, 0)
    assert p.fraction() == pytest.approx(0.5)
    assert p.remaining_s() == pytest.approx(total - motion[0].total_s / 2)
    assert "[##########----------]  50 %" in out.getvalue()
    p.update(motion[0].total_s * 3, _state(2.0), 200, 0)  # overran its estimate
    assert p.fraction() == pytest.approx(0.99)
    assert p.remaining_s() == pytest.approx(total - motion[0].total_s)
    p.step_finished(motion[0].step)
    assert p.remaining_s() == pytest.approx(total - motion[0].total_s)


def test_plain_lines_when_not_a_terminal(plan) -> None:
    out, wall = io.StringIO(), Wall()
    p = Progress(out, wall=wall, interval_s=10.0)
    assert not p.tty
    drive(p, plan, wall, n_steps=3, wall_per_poll=0.5, drop_every=7)
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.strip("\n").split("\n")
    starts = [ln for ln in lines if " started: " in ln]
    ends = [ln for ln in lines if " done: " in ln]
    periodic = [ln for ln in lines if " % | left ~" in ln]
    assert len(starts) == 3 and len(ends) == 3
    polls = sum(int(round(e.total_s / 0.5)) for e in [e for e in plan if e.step.is_motion][:3])
    wall_s = polls * 0.5
    # one line every 10 s of wall time (the start line resets the timer, so at most this many)
    assert int(wall_s // 10) - 3 <= len(periodic) <= int(wall_s // 10) + 1
    assert starts[0].startswith("[1/25] started: warmup warm-up, estimate ")
    assert " samples; left ~" in ends[0]
    assert lines[-1].startswith("complete: 3/25 steps") and "dropped" in lines[-1]
    dropped = [int(ln.rsplit("dropped ", 1)[1]) for ln in periodic]
    assert dropped == sorted(dropped) and dropped[-1] > 0


def test_messages_do_not_tear_the_bar(plan) -> None:
    out, wall = FakeTTY(), Wall()
    p = Progress(out, wall=wall, width=400)
    p.start(plan)
    p.step_started(plan[0].step)
    p.update(1.0, _state(1.0), 100, 0)
    out.seek(0)
    out.truncate()
    print("warning: pulse source: link lost", file=p.console, flush=True)
    text = out.getvalue()
    # the bar is cleared, the message gets its own line, then the bar is redrawn below it
    assert text.startswith("\r\x1b[Kwarning: pulse source: link lost\n\r[1/25] ")


def test_counter_gaps_and_null_progress(plan) -> None:
    g = CounterGaps()
    assert g.add(np.arange(0, 10)) == 0
    assert g.add(np.array([10, 11, 15, 16])) == 3  # 12, 13, 14 missing
    assert g.add(np.array([20])) == 6  # gap across blocks: 17, 18, 19
    assert g.add(np.array([], dtype=np.uint64)) == 6
    sink = io.StringIO()
    n = NullProgress()
    drive(n, plan, Wall())
    n.message("hidden")
    assert sink.getvalue() == ""
    passthrough = io.StringIO()
    q = make_progress(passthrough, enabled=False)
    drive(q, plan, Wall())
    print("a log line", file=q.console)
    assert passthrough.getvalue() == "a log line\n"  # log lines still pass, no progress output


def test_work_progress_bar_on_a_terminal_lines_otherwise() -> None:
    wall = Wall()
    tty = FakeTTY()
    p = WorkProgress("allan x.h5, 6 axes", 1000, stream=tty, wall=wall)
    for done in (100, 400, 700):
        wall.t += 1.0
        p.update(done)
    shown = screen(tty.getvalue())
    assert len(shown) == 1 and shown[0].startswith("[##############------] allan x.h5, 6 axes: 700/1,000")
    assert "70 %" in shown[0] and "233 samples/s" in shown[0] and "left ~1.29 s" in shown[0]  # 700 in 3 s
    p.finish()
    assert screen(tty.getvalue())[-1] == "allan x.h5, 6 axes: 700 samples in 3 s"
    plain = io.StringIO()
    wall2 = Wall()
    q = WorkProgress("fit", 100, unit="taus", stream=plain, wall=wall2, interval_s=10.0)
    for done in range(0, 101, 10):
        wall2.t += 3.0
        q.update(done)
    lines = plain.getvalue().splitlines()
    assert "\r" not in plain.getvalue() and len(lines) == 3  # 11 calls over 30 s: at most one line per 10 s
    assert lines[0].startswith("fit: 0/100 taus (0 %)")
    silent = io.StringIO()
    WorkProgress("off", 10, stream=silent, enabled=False).update(5)
    assert silent.getvalue() == ""


def test_a_resumed_run_numbers_its_steps_in_the_whole_procedure(plan) -> None:
    """A resume after five finished motion steps: its first step is [6/25], not [1/20], and the
    counts say how many are left of the whole (the runner passes done_before)."""
    motion = [e for e in plan if e.step.is_motion]
    assert len(motion) == 25
    rest = [e for e in plan if e.step.index >= motion[5].step.index]
    out, wall = io.StringIO(), Wall()
    p = Progress(out, wall=wall, interval_s=10.0)
    p.start(rest, "24pos", done_before=5)
    p.update(0.0, _state(0.0), 0, 0)
    p.step_started(motion[5].step)
    p.update(motion[5].total_s, _state(1.0), 100, 0)
    p.step_finished(motion[5].step, Seg(0, 100))
    p.finish("complete")
    lines = out.getvalue().strip("\n").split("\n")
    assert lines[0].startswith("24pos: 20 of 25 steps left, about "), lines[0]
    assert [ln.split(" ", 1)[0] for ln in lines if " started: " in ln or " done: " in ln] == ["[6/25]", "[6/25]"]
    assert lines[-1].startswith("complete: 6/25 steps"), lines[-1]
