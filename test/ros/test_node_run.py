"""vo_node's entry point (epi_vo.ros.node_run.run_node) around rclpy's spin, with rclpy's calls stood in for:
no DDS is started here."""

from __future__ import annotations

from typing import Any

import pytest

from epi_vo.ros import node_run


class _Node:
    destroyed = False

    def destroy_node(self) -> None:
        self.destroyed = True


def _stand_in(monkeypatch: pytest.MonkeyPatch, spin: Any, ok: bool) -> list[str]:
    calls: list[str] = []
    monkeypatch.setattr(node_run.rclpy, "init", lambda args=None: calls.append("init"))
    monkeypatch.setattr(node_run.rclpy, "spin", spin)
    monkeypatch.setattr(node_run.rclpy, "ok", lambda context=None: ok)
    monkeypatch.setattr(node_run.rclpy, "try_shutdown", lambda context=None: calls.append("shutdown"))
    return calls


def _context_gone(node: Any) -> None:
    raise node_run.RCLError("failed to initialize wait set: the given context is not valid")


def test_a_context_shut_down_under_spin_is_a_stop_not_a_traceback(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C landing while the executor makes its wait set: rcl says the context is not valid."""
    calls = _stand_in(monkeypatch, _context_gone, ok=False)
    node = _Node()
    node_run.run_node(lambda: node, "vo_node", "", ["--ros-args"])
    assert node.destroyed and calls == ["init", "shutdown"]


def test_an_rcl_error_with_the_context_still_up_is_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = _stand_in(monkeypatch, _context_gone, ok=True)
    node = _Node()
    with pytest.raises(node_run.RCLError):
        node_run.run_node(lambda: node, "vo_node", "", ["--ros-args"])
    assert node.destroyed and calls == ["init", "shutdown"]
