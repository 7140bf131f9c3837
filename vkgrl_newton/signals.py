"""Stop signals as interrupts: SIGTERM (kill, a scheduler's pre-emption, `docker stop`, Ray
stopping a sweep's trial) and SIGHUP (a closed terminal) end a command the way Ctrl-C does, through
its KeyboardInterrupt path (checkpoint, clean exit), instead of killing it mid-write.

    with stop_signals_as_interrupts():  # the previous handlers come back after the block
        try: ...
        except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM or SIGHUP
            return exit_code(e)         # 130, 143 or 129 (128 + the signal's number, as a shell reports it)

A long phase says what a stop inside it leaves, for the command's one line (`stop_line`):

    with phase("recording the demonstrations", "none is kept"):  # an inner phase's words win
        ...
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable
from contextlib import contextmanager

__all__ = ["StopSignal", "stop_signals_as_interrupts", "exit_code", "describe", "run_cli", "STOP_EXIT_CODES", "phase",
           "where", "stop_line", "stop_exits"]

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
def stop_signals_as_interrupts(keep_handlers: bool = False):
    """Inside the block SIGTERM and SIGHUP raise StopSignal (a KeyboardInterrupt) in the main
    thread; outside a main thread (where Python cannot set handlers) nothing changes.
    keep_handlers: only where the signal would kill the process (its default handler): a library
    call in someone's program keeps the handlers the program set."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in STOP_SIGNALS
                if not keep_handlers or signal.getsignal(s) is signal.SIG_DFL}
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


@contextmanager
def phase(what: str, kept: str | Callable[[], str]):
    """A stop inside the block carries `what` was under way and what of it is `kept` (a callable:
    asked at the stop) to the command's one line (`where`, `stop_line`). The innermost phase's
    words win: the owner of the work knows best what it leaves."""
    try:
        yield
    except KeyboardInterrupt as e:
        if getattr(e, "phase", None) is None:
            e.phase = (what, kept() if callable(kept) else kept)
        raise


def where(exc: BaseException) -> str:
    """' while <phase> (<what is kept>)' of a stop raised inside a `phase`, else ''."""
    tag = getattr(exc, "phase", None)
    return f" while {tag[0]} ({tag[1]})" if tag else ""


def stop_line(prog: str, exc: BaseException, then: str) -> str:
    """`<prog>: stopped by SIGTERM while <phase> (<what is kept>); <then>`: a stopped command's one line."""
    return f"{prog}: {describe(exc)}{where(exc)}; {then}"


@contextmanager
def stop_exits(prog: str, then: str):
    """For library code that prepares cache files inside someone's program (gymnasium.make): in the
    block SIGTERM and SIGHUP raise StopSignal where they would kill the process (the program's own
    handlers stay), so that the preparation's cleanup runs; a stop (Ctrl-C too) then prints one line
    (`stop_line`) and exits 130, 143 or 129 as the command lines do (SystemExit: no traceback)."""
    with stop_signals_as_interrupts(keep_handlers=True):
        try:
            yield
        except KeyboardInterrupt as e:
            print(stop_line(prog, e, then), file=sys.stderr)
            raise SystemExit(exit_code(e)) from None


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
