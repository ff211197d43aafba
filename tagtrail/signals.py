"""Ctrl-C, SIGTERM and SIGHUP end a ``tagtrail`` command within a second, with one line.

SIGINT: exit 130 and ``interrupted`` on stderr; SIGTERM and SIGHUP: exit 143 / 129 (128 + the
signal's number, as a shell reports a process it ended) and ``interrupted by SIGTERM`` /
``interrupted by SIGHUP``. A signal the parent process set to be ignored (``nohup``, a job
started with ``&`` by a non-interactive shell) stays ignored.

The handler raises :class:`Interrupted` (a :class:`KeyboardInterrupt`) in the main thread, so
the command unwinds through its ``finally`` blocks (temporary files removed) up to
:func:`tagtrail.cli.run_command`, which prints the line. Where Python would print and drop that
exception (the signal arrived inside a garbage-collector callback or a finalizer) the signal is
delivered again a few milliseconds later instead. A watchdog thread started by the same
signal ends the process :data:`GRACE_S` later whatever the main thread is still doing (a stage
running in a thread, a Dask cluster closing); a second signal ends it at once. Ending there
leaves what ``kill -9`` leaves, which every writer tolerates: artifacts and outputs are renamed
into place whole, and the next run removes the temporary files. The handlers are installed by
the console script only (:func:`install`); ``tagtrail.cli.main`` called in-process keeps
Python's own Ctrl-C (a plain ``KeyboardInterrupt``, still exit 130 and one line).
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import NoReturn

GRACE_S = 0.5  # unwinding time before the watchdog ends the process
REDELIVER_S = 0.005  # a signal that came during a GC callback or finalizer: delivered again
HANDLED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

_lock = threading.RLock()
_AT_EXIT: list[Callable[[], None]] = []
_state: dict[str, object] = {"signum": None, "reported": False, "finished": False}


class Interrupted(KeyboardInterrupt):
    """A termination signal arrived: SIGINT, SIGTERM or SIGHUP (``signum``)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def signum_of(err: BaseException) -> int:
    """The signal behind ``err`` (a plain ``KeyboardInterrupt`` is Ctrl-C)."""
    return err.signum if isinstance(err, Interrupted) else int(signal.SIGINT)


def message(signum: int) -> str:
    """The one line: ``interrupted`` for Ctrl-C, ``interrupted by SIGTERM`` for the others."""
    if signum == signal.SIGINT:
        return "interrupted"
    return f"interrupted by {signal.Signals(signum).name}"


def report(err: BaseException) -> int:
    """Print the interrupt's line on stderr (once per process) and return its exit code."""
    signum = signum_of(err)
    with _lock:
        if not _state["reported"]:
            _state["reported"] = True
            _clear_progress_bars()
            print(message(signum), file=sys.stderr, flush=True)
    return 128 + signum


def _clear_progress_bars() -> None:
    """Erase the progress bars still drawn, so the line stands on a line of its own."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())):
        try:
            bar.leave = False
            bar.close()
        except Exception:  # noqa: BLE001 - a bar that cannot be erased stays
            pass


def at_exit(callback: Callable[[], None]) -> None:
    """Call ``callback`` just before an interrupted process ends (e.g. stop worker processes:
    they would otherwise finish their task for nobody)."""
    _AT_EXIT.append(callback)


def _end(code: int) -> NoReturn:
    for callback in _AT_EXIT:
        try:
            callback()
        except Exception:  # noqa: BLE001 - ending anyway
            pass
    _flush()
    os._exit(code)


def leave(signum: int) -> NoReturn:
    """Report the interrupt (unless done already) and end the process now."""
    with _lock:
        report(Interrupted(signum))
        _end(128 + signum)


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass


def _watchdog(signum: int) -> None:
    time.sleep(GRACE_S)
    leave(signum)


def _swallowed(frame: FrameType | None) -> bool:
    """Whether an exception raised at ``frame`` would be printed and dropped ("Exception
    ignored in ...") instead of unwinding the command: inside a garbage-collector callback
    (dask's ``distributed`` registers one) or a finalizer (``__del__``)."""
    codes = {getattr(getattr(cb, "__func__", cb), "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def _redeliver(signum: int) -> None:
    time.sleep(REDELIVER_S)
    signal.pthread_kill(threading.main_thread().ident or 0, signum)


def _handler(signum: int, frame: FrameType | None) -> None:
    if _swallowed(frame):  # raise once the callback has returned: the signal again, shortly
        threading.Thread(target=_redeliver, args=(signum,), daemon=True).start()
        return
    with _lock:
        first = _state["signum"] is None and not _state["finished"]
        if first:
            _state["signum"] = signum
    if not first:  # a second signal, or one after the command finished
        leave(signum)
    threading.Thread(
        target=_watchdog, args=(signum,), name="tagtrail-interrupt", daemon=True
    ).start()
    raise Interrupted(signum)


def install() -> None:
    """Handle SIGINT, SIGTERM and SIGHUP as above (main thread; ignored signals stay ignored)."""
    for sig in HANDLED:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _handler)


def finished() -> None:
    """The command is over: a signal from now on ends the process at once with its line and
    code (no ``KeyboardInterrupt`` in the interpreter's exit: Python would die of the signal,
    exit -2 and no line)."""
    with _lock:
        _state["finished"] = True


def finish(code: int) -> NoReturn:
    """End the process with ``code``. After an interrupt at once (threads still running a stage
    are abandoned, as ``kill -9`` would); else through the normal exit (:func:`finished`)."""
    finished()
    with _lock:
        interrupted = bool(_state["reported"])
    if interrupted:
        _end(code)
    sys.exit(code)
