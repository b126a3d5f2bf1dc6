"""drvs.core.backoff: the one exponential backoff every retry loop takes its waits from."""

from __future__ import annotations

import pytest

from drvs.core.backoff import Backoff, waits


def test_waits_double_up_to_the_longest() -> None:
    assert list(waits(0.2, 1.0, 6)) == [0.2, 0.4, 0.8, 1.0, 1.0, 1.0]
    assert list(waits(0.2, 1.0, 0)) == []


def test_a_success_starts_again_from_the_first_wait() -> None:
    b = Backoff(0.1, 5.0)
    assert not b.failing
    assert [b.next(), b.next(), b.next()] == [0.1, 0.2, 0.4]
    assert b.failing and b.current == 0.8
    b.reset()
    assert not b.failing and b.next() == 0.1


def test_one_failure_may_cap_the_wait_after_it_differently() -> None:
    b = Backoff(1.0, 5.0)
    assert b.next(max_s=1.5) == 1.0  # (the heartbeat interval caps an unreachable server's waits)
    assert b.current == 1.5
    assert b.next() == 1.5 and b.current == 3.0


def test_a_backoff_that_cannot_back_off_is_refused() -> None:
    with pytest.raises(ValueError, match="initial_s"):
        Backoff(0.0, 1.0)
    with pytest.raises(ValueError, match="initial_s"):
        Backoff(2.0, 1.0)
