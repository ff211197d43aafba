"""Functions the worker-pool tests run in worker processes (importable by module path)."""

from __future__ import annotations

import os

from tagtrail.errors import SourceError


def square(x: int) -> tuple[int, int]:
    print("stray output must not corrupt the result stream")
    return x, x * x


def fail(x: int) -> int:
    raise SourceError(f"bad frame {x}")


def die(x: int) -> int:
    os._exit(3)
