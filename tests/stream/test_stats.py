"""The nodes' console lines (tagtrail.stream.stats.say)."""

from __future__ import annotations

import sys

import pytest

from tagtrail.stream.stats import say


def test_say_writes_a_line_in_one_write(monkeypatch: pytest.MonkeyPatch) -> None:
    """Nodes started together share a terminal: each line leaves in one write, so an
    unbuffered stdout (``print`` writes the text and its newline apart) cannot run another
    node's line into it."""
    writes: list[str] = []

    class Out:
        def write(self, s: str) -> int:
            writes.append(s)
            return len(s)

        def flush(self) -> None:
            writes.append("<flush>")

    monkeypatch.setattr(sys, "stdout", Out())
    say("relocalize: ready")
    assert writes == ["relocalize: ready\n", "<flush>"]
