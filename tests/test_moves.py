"""Moves of independent devices at once (procedures/moves.py): they overlap, a failure of one stops
the others, an abort stops all of them."""

from __future__ import annotations

import _thread
import threading
from contextlib import contextmanager

import pytest

from drivers.errors import DeviceFault
from procedures.moves import Move, move_together


class Run:
    def __init__(self) -> None:
        self.bars: list[str] = []
        self.fractions: list[float] = []

    @contextmanager
    def move(self, description):
        self.bars.append(description)
        yield self.fractions.append


class Axis:
    """A device whose move lasts until it is stopped or `release` is set."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.started = threading.Event()
        self.release = threading.Event()
        self.stops = 0

    def stop(self) -> None:
        self.stops += 1
        self.release.set()

    def go(self, progress) -> None:
        self.started.set()
        progress(0.5)
        if not self.release.wait(10.0):
            raise AssertionError(f"{self.name} was never released")
        progress(1.0)


def test_the_moves_overlap_and_all_arrive():
    a, b = Axis("turntable"), Axis("stewart")

    def go_a(progress):
        # b must be moving while a is: sequential moves would wait here for 10 s and fail
        assert b.started.wait(10.0), "the second move did not start while the first was under way"
        b.release.set()
        a.release.set()
        a.go(progress)

    run = Run()
    move_together(run, [Move(a, "turntable to +30 deg", go_a), Move(b, "Stewart platform", b.go)])
    assert run.bars == ["turntable to +30 deg + Stewart platform"]
    assert a.stops == b.stops == 0
    assert max(run.fractions) == 1.0


def test_a_fault_of_one_stops_the_other_and_is_the_error():
    a, b = Axis("turntable"), Axis("stewart")

    def faulty(progress):
        assert b.started.wait(10.0)
        raise DeviceFault("turntable", 40, "fault overcurrent at 12.000 deg", "to 30.000 deg")

    with pytest.raises(DeviceFault) as info:
        move_together(Run(), [Move(a, "turntable", faulty), Move(b, "Stewart platform", b.go)])
    assert b.stops == 1 and a.stops == 0     # the faulty driver stops its own device
    assert "overcurrent" in str(info.value) and "meanwhile stewart: motion stopped" in str(info.value)


def test_an_abort_stops_every_device_still_moving():
    a, b = Axis("turntable"), Axis("stewart")

    def interrupted(progress):
        assert b.started.wait(10.0)
        _thread.interrupt_main()      # Ctrl-C reaches the main thread, which only waits
        a.release.wait(10.0)

    with pytest.raises(KeyboardInterrupt) as info:
        move_together(Run(), [Move(a, "turntable", interrupted), Move(b, "Stewart platform", b.go)])
    assert a.stops == 1 and b.stops == 1
    assert any("turntable: motion stopped" in n and "stewart: motion stopped" in n
               for n in getattr(info.value, "__notes__", []))


def test_one_move_needs_no_thread():
    a = Axis("turntable")
    seen = []

    def go(progress):
        seen.append(threading.current_thread() is threading.main_thread())

    run = Run()
    move_together(run, [Move(a, "turntable", go)])
    move_together(run, [])
    assert seen == [True] and run.bars == ["turntable"]


def test_an_abort_before_every_move_has_started_stops_what_started(monkeypatch):
    a, b = Axis("turntable"), Axis("stewart")
    starts = []
    real_start = threading.Thread.start

    def start(self):
        starts.append(self.name)
        if len(starts) == 2:
            raise KeyboardInterrupt("signal 2")     # the second Ctrl-C, between the two starts
        real_start(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    with pytest.raises(KeyboardInterrupt):
        move_together(Run(), [Move(a, "turntable", a.go), Move(b, "Stewart platform", b.go)])
    assert a.stops == 1 and b.stops == 0
