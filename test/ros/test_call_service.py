"""The test probes' service call (ros_fixtures.call_service) against a stand-in client that loses
responses, as DDS can when a response is sent before the client's response reader is matched."""

from __future__ import annotations

import time
from typing import Any

import pytest
import ros_fixtures
from ros_fixtures import call_service


class _Future:
    def __init__(self, answer: Any) -> None:
        self.answer = answer

    def done(self) -> bool:
        return self.answer is not None

    def result(self) -> Any:
        return self.answer


class _Client:
    """Answers request k with answers[k]; None is a lost response."""

    srv_name = "/stand_in"

    def __init__(self, answers: list[Any]) -> None:
        self.answers = answers
        self.sent = 0

    def wait_for_service(self, timeout_sec: float) -> bool:
        return True

    def call_async(self, request: Any) -> _Future:
        answer = self.answers[min(self.sent, len(self.answers) - 1)]
        self.sent += 1
        return _Future(answer)


class _Executor:
    def spin_once(self, timeout_sec: float) -> None:
        time.sleep(timeout_sec)


@pytest.fixture(autouse=True)
def _short_resend(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ros_fixtures, "RESEND_S", 0.05)


def test_a_lost_response_is_asked_for_again() -> None:
    client = _Client([None, None, "answer"])
    assert call_service(_Executor(), client, object(), timeout_s=30) == "answer"
    assert client.sent == 3


def test_an_answered_request_is_sent_once() -> None:
    client = _Client(["answer"])
    assert call_service(_Executor(), client, object(), timeout_s=30) == "answer"
    assert client.sent == 1


def test_a_request_that_took_effect_is_not_sent_again() -> None:
    client = _Client([None, "second answer"])
    assert call_service(_Executor(), client, object(), timeout_s=30, took_effect=lambda: True) is None
    assert client.sent == 1


def test_no_response_at_all_fails_within_the_bound() -> None:
    client = _Client([None])
    with pytest.raises(AssertionError, match="/stand_in: no response"):
        call_service(_Executor(), client, object(), timeout_s=0.3)
    assert client.sent >= 1
