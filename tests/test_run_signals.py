"""RunSignals (rigctl.run.runner): a re-delivered interruption never lands on top of the one the
analysis is already handling. The re-delivery thread (REDELIVER_S) can fire in the window between
the first AnalysisInterrupted being raised and _analyse's ``except`` clause clearing ``pending``;
a second raise there would escape _analyse as an uncaught exception."""
from __future__ import annotations

import signal

import pytest

from rigctl.run.runner import AnalysisInterrupted, RunSignals


def test_first_signal_during_analysis_raises() -> None:
    s = RunSignals(analysing=True)
    with pytest.raises(AnalysisInterrupted):
        s.received(signal.SIGINT)
    assert s.pending and s.names == ["SIGINT"]
    s.analysing = s.pending = False  # as _analyse does; the re-delivery thread then ends


def test_redelivery_while_the_interruption_is_handled_does_not_raise_again() -> None:
    s = RunSignals(analysing=True)
    try:
        s.received(signal.SIGTERM)
    except AnalysisInterrupted:
        # the main thread is in the handler of the first interruption; the re-delivery
        # thread's interrupt_main runs the handler here before `pending` is cleared
        s._again = True
        s.received(signal.SIGTERM)  # must return, not raise a second AnalysisInterrupted
    assert s.names == ["SIGTERM", "SIGTERM"]
    s.analysing = s.pending = False


def test_redelivery_of_a_dropped_interruption_raises() -> None:
    s = RunSignals(analysing=True)
    try:
        s.received(signal.SIGINT)
    except AnalysisInterrupted:
        pass  # dropped (as Python drops one raised in a weakref callback)
    s._again = True  # the re-delivery thread, outside any handler of it
    with pytest.raises(AnalysisInterrupted):
        s.received(signal.SIGINT)
    s.analysing = s.pending = False
