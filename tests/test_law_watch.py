"""The law's code watched on the rig (host/experiment/law_watch.py), in process: its value and its
exception handed back, the time limit naming the law, a hold of the interpreter measured and blamed
for a lost heartbeat.  Fast (a few seconds); the rig itself: tests/test_api_rig_law_time.py."""

from __future__ import annotations

import threading
import time

import pytest

from host.experiment.law_watch import LAW_LIMIT_ENV, LAW_UPDATE_LIMIT_S, LawWatch, law_update_limit_s
from host.learning.laws.checked import LawError


def busy(seconds: float) -> int:
    t0, x = time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        x += 1
    return x


def test_the_value_and_the_exception_come_back() -> None:
    watch = LawWatch("w", limit_s=10.0)
    assert watch.call(lambda: 42, 0) == 42
    with pytest.raises(ZeroDivisionError):
        watch.call(lambda: 1 / 0, 1)
    assert watch.last is not None and watch.last.after_trial == 1


def test_past_the_limit_the_law_is_named_with_where_it_was() -> None:
    watch = LawWatch("slow-law", limit_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(LawError, match=r"law slow-law did not return from its update after trial 3 within the limit") as caught:
        watch.call(lambda: busy(3.0), 3)
    assert time.monotonic() - t0 < 2.5
    assert "in busy" in str(caught.value.__cause__)  # the law's stack, for logs/law-error.log


def test_pure_python_lets_other_threads_run_a_gil_holding_call_is_blamed() -> None:
    beats: list[float] = []
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(0.01):
            beats.append(time.monotonic())

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        watch = LawWatch("w", limit_s=60.0)
        watch.call(lambda: busy(1.0), 0)  # the waiting thread wakes meanwhile: the interpreter switches
        assert watch.last is not None and watch.last.held_s < 0.9
        watch.consumer_s = 0.95
        assert watch.blame("the host's heartbeat was lost") == "the host's heartbeat was lost"
        n = 1
        while True:  # one C call that holds the GIL for more than 0.55 s, measured on the watched call
            # itself (a calibration beforehand assumed the machine keeps its speed: beside CPU hogs
            # the same call ran 0.44 s after 0.5 s)
            watch.call(lambda n=n: sum(range(n)), 2)  # the waiting thread cannot wake until it returns
            assert watch.last is not None
            if watch.last.seconds > 0.55:
                break
            n *= 4
        assert watch.last is not None and watch.last.held_s > 0.45
        watch.consumer_s = 0.45
        blamed = watch.blame("the host's heartbeat was lost")
        assert "during law w's update after trial 2 the host's threads did not run for" in blamed
    finally:
        stop.set()
        thread.join()


def test_the_limit_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LAW_LIMIT_ENV, "2.5")
    assert law_update_limit_s() == 2.5
    monkeypatch.setenv(LAW_LIMIT_ENV, "soon")
    assert law_update_limit_s() == LAW_UPDATE_LIMIT_S
