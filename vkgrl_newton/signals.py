"""Stop signals as interrupts: SIGTERM (kill, a scheduler's pre-emption, `docker stop`, Ray
stopping a sweep's trial) and SIGHUP (a closed terminal) end a command the way Ctrl-C does, through
its KeyboardInterrupt path (checkpoint, clean exit), instead of killing it mid-write.

    with stop_signals_as_interrupts():  # the previous handlers come back after the block
        try: ...
        except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM or SIGHUP
            return exit_code(e)         # 130, 143 or 129 (128 + the signal's number, as a shell reports it)
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager

__all__ = ["StopSignal", "stop_signals_as_interrupts", "exit_code", "describe", "run_cli", "STOP_EXIT_CODES"]

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
STOP_EXIT_CODES = (130, 128 + signal.SIGTERM, 128 + signal.SIGHUP)  # what a stopped command exits with


class StopSignal(KeyboardInterrupt):
    """A stop signal received; `signum` says which."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


_received: list[int] = []  # the stop signals received in this process (a library may re-raise a plain
# KeyboardInterrupt in place of ours, Ray's wait does: exit_code still knows which signal it was)


def _raise(signum, frame):
    _received.append(signum)
    raise StopSignal(signum)


@contextmanager
def stop_signals_as_interrupts():
    """Inside the block SIGTERM and SIGHUP raise StopSignal (a KeyboardInterrupt) in the main
    thread; outside a main thread (where Python cannot set handlers) nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():  # None: a handler set from C, not restorable: the default
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


def exit_code(exc: BaseException) -> int:
    """128 + the signal's number for a stop signal, 130 for Ctrl-C."""
    if isinstance(exc, StopSignal):
        return 128 + exc.signum
    return 128 + _received[-1] if _received else 130


def describe(exc: BaseException) -> str:
    """'stopped by SIGTERM' (or SIGHUP) or 'interrupted' (Ctrl-C), for a log line."""
    if isinstance(exc, StopSignal):
        return str(exc)
    return f"stopped by {signal.Signals(_received[-1]).name}" if _received else "interrupted"


def run_cli(main, prog: str, on_stop: str = "nothing was written") -> int:
    """A command's main() with SIGTERM and SIGHUP handled like Ctrl-C: a stop prints one line,
    `<prog>: interrupted; <on_stop>` (or 'stopped by SIGTERM'), no traceback, and the exit code is
    130, 143 or 129. For the commands that write their result once, at the end (main() cleans up
    anything partial before the interrupt propagates)."""
    with stop_signals_as_interrupts():
        try:
            return main()
        except KeyboardInterrupt as e:
            print(f"{prog}: {describe(e)}; {on_stop}", file=sys.stderr)
            return exit_code(e)
