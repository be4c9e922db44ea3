"""The progress bar on a real terminal: a tmux pane (issue 9). Skips when tmux is absent."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest

from helpers import ROOT, rigctl_cmd

TMUX = shutil.which("tmux")
pytestmark = pytest.mark.skipif(TMUX is None, reason="tmux is not installed (apt-get install tmux)")
BAR = re.compile(r"\[(\d+)/(\d+)\] .*\[[#-]{20}\]\s+(\d+) %")

SCRIPT = textwrap.dedent("""
    import os, sys, time
    from dataclasses import dataclass
    from pathlib import Path
    import numpy as np
    from rigctl.devices import TableState
    from rigctl.progress import Progress

    @dataclass
    class Step:
        index: int
        kind: str
        label: str
        is_motion: bool = True

    @dataclass
    class Est:
        step: Step
        total_s: float

    shown, seen = Path(sys.argv[1]), Path(sys.argv[2])

    def handshake(k):
        # update k is drawn: wait until the test has captured the pane since
        tmp = shown.with_suffix(".tmp")
        tmp.write_text(str(k))
        os.replace(tmp, shown)
        while not (seen.exists() and seen.read_text() and int(seen.read_text()) >= k):
            time.sleep(0.01)

    plan = [Est(Step(0, "warmup", "warm-up"), 20.0), Est(Step(1, "orientation", "x north"), 10.0)]
    p = Progress()  # stdout: the tmux pane, a real terminal
    assert p.tty, "stdout is not a terminal"
    p.start(plan, "tmux-test")
    t, k = 0.0, 0
    for e in plan:
        p.step_started(e.step)
        for _ in range(int(e.total_s)):
            t += 1.0
            time.sleep(p.min_redraw_s)  # the bar's own rate limit has passed: this update is drawn
            p.update(t, TableState(t, np.radians([0.0, 90.0, 3.0 * t]), np.zeros(3), (0, 0, 0)),
                     int(100 * t), 0)
            sys.stdout.flush()
            k += 1
            handshake(k)
        p.step_finished(e.step)
    p.finish("complete")
    sys.stdout.flush()
    time.sleep(30)
""")


class Pane:
    def __init__(self, tmp: Path, command: list[str], width: int = 160, height: int = 20) -> None:
        self.sock = f"rigctl-test-{uuid.uuid4().hex[:8]}"
        self.tmp = tmp
        env = dict(os.environ, TERM="xterm")
        subprocess.run([TMUX, "-L", self.sock, "new-session", "-d", "-s", "t", "-x", str(width),
                        "-y", str(height), *command], check=True, env=env, cwd=ROOT, timeout=20)

    def capture(self) -> list[str]:
        r = subprocess.run([TMUX, "-L", self.sock, "capture-pane", "-p", "-t", "t"],
                           capture_output=True, text=True, timeout=20)
        return r.stdout.splitlines()

    def close(self) -> None:
        subprocess.run([TMUX, "-L", self.sock, "kill-server"], capture_output=True, timeout=20)


def _watch(pane: Pane, until: str, stall_s: float = 60.0, every_s: float = 0.1) -> list[list[str]]:
    """Capture the pane every ``every_s`` until a line contains ``until``, or until the pane has
    not changed for ``stall_s`` of wall time (a loaded host takes longer, a stuck one stops)."""
    shots: list[list[str]] = []
    since = time.monotonic()
    while time.monotonic() - since < stall_s:
        shot = pane.capture()
        if not shots or shot != shots[-1]:
            since = time.monotonic()
        shots.append(shot)
        if any(until in ln for ln in shot):
            break
        time.sleep(every_s)
    return shots


def test_bar_redraws_in_place_on_a_terminal(tmp_path: Path) -> None:
    """The script draws an update, then waits until the test has captured the pane, so every
    state of the bar is seen however slow the host (it paced itself by 0.1 s of wall time before,
    and a capture that took longer missed states; the whole was timed by 30 s of wall time that
    the script's start-up took 15 s of at load 20)."""
    script, shown, acked = tmp_path / "drive.py", tmp_path / "shown", tmp_path / "seen"
    script.write_text(SCRIPT)
    pane = Pane(tmp_path, [sys.executable, str(script), str(shown), str(acked)])
    shots: list[list[str]] = []
    try:
        last, since = None, time.monotonic()
        while True:
            k = shown.read_text() if shown.exists() else ""
            shot = pane.capture()
            shots.append(shot)
            if any("complete: 2/2 steps" in ln for ln in shot):
                break
            if k:
                tmp = acked.with_suffix(".tmp")
                tmp.write_text(k)
                os.replace(tmp, acked)
            if k != last:
                last, since = k, time.monotonic()
            assert time.monotonic() - since < 60, f"the script stopped at update {k!r}: {shot}"
            time.sleep(0.02)
    finally:
        pane.close()
    final = shots[-1]
    assert any(ln.startswith("complete: 2/2 steps") for ln in final), final
    seen = set()
    for shot in shots:
        bars = [m for m in (BAR.search(ln) for ln in shot) if m]
        assert len(bars) <= 1, f"the bar scrolled instead of redrawing in place: {shot}"
        if bars:
            seen.add((bars[0].group(1), bars[0].group(3)))
    assert len(seen) >= 4, f"the bar did not update: {sorted(seen)}"
    assert {s for s, _ in seen} >= {"1", "2"}, sorted(seen)
    # finished steps left one plain line each; the bar is gone after finish
    assert [ln.split(" ", 1)[0] for ln in final if " done: " in ln] == ["[1/2]", "[2/2]"]
    assert not any(BAR.search(ln) for ln in final)


def test_rigctl_run_shows_the_bar_on_a_terminal(tmp_path: Path) -> None:
    cmd = [*rigctl_cmd(), "run", "procedures/24pos.yaml", "-p", "warmup=1 min", "-p", "sample=5 s",
           "--out", str(tmp_path / "runs")]
    wrapper = [sys.executable, "-c", "import subprocess, sys, time; "
               f"rc = subprocess.call({cmd!r}); print('EXIT', rc, flush=True); time.sleep(30)"]
    pane = Pane(tmp_path, wrapper)
    try:
        shots = _watch(pane, "EXIT ")
    finally:
        pane.close()
    assert any("EXIT 0" in ln for ln in shots[-1]), shots[-1]
    bars = {m.group(0) for shot in shots for m in (BAR.search(ln) for ln in shot) if m}
    assert len(bars) >= 2, "no progress bar seen during rigctl run"
