"""Fault injection for the crash tests: ``TAGTRAIL_FAULT=kill@<point>`` kills the process with
SIGKILL when it reaches ``<point>`` (e.g. ``stage:optimize``, ``store:pnp``, ``export:map.png``);
``SIGINT@<point>`` (or ``SIGTERM@``, ``SIGHUP@``) sends the process that signal there, as a
Ctrl-C at that moment would (``cli:exit``: after the command finished, before the process ends).

The points sit where a real crash does the most harm (results computed but not stored, an
entry half written, an output file half exported), so tests can prove that a rerun recovers
byte for byte. Unset (always, outside tests), a point costs one dictionary lookup.
"""

from __future__ import annotations

import os
import signal
import time

ENV = "TAGTRAIL_FAULT"


SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")


def point(name: str) -> None:
    """Die here, as ``kill -9`` would, if ``TAGTRAIL_FAULT`` is ``kill@<name>``; signal this
    process if it is ``SIGINT@<name>`` (``SIGTERM``, ``SIGHUP``); pause here for S seconds if it
    is ``sleep@<name>=S`` (to widen a race window in a test)."""
    fault = os.environ.get(ENV)
    if fault is None:
        return
    action, _, where = fault.partition("@")
    if action == "sleep" and where.rpartition("=")[0] == name:
        time.sleep(float(where.rpartition("=")[2]))
        return
    if where != name:
        return
    if action == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    elif action in SIGNALS:
        os.kill(os.getpid(), getattr(signal, action))
