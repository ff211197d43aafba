"""Fault injection for the crash tests: ``TAGTRAIL_FAULT=kill@<point>`` kills the process with
SIGKILL when it reaches ``<point>`` (e.g. ``stage:optimize``, ``store:pnp``, ``export:map.png``).

The points sit where a real crash does the most harm (results computed but not stored, an
entry half written, an output file half exported), so tests can prove that a rerun recovers
byte for byte. Unset (always, outside tests), a point costs one dictionary lookup.
"""

from __future__ import annotations

import os
import signal

ENV = "TAGTRAIL_FAULT"


def point(name: str) -> None:
    """Die here, as ``kill -9`` would, if ``TAGTRAIL_FAULT`` is ``kill@<name>``."""
    fault = os.environ.get(ENV)
    if fault is not None and fault == f"kill@{name}":
        os.kill(os.getpid(), signal.SIGKILL)
