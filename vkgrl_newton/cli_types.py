"""argparse value types shared by the scripts in train/: a bad value is an argparse error naming the flag."""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import tempfile
from contextlib import contextmanager

__all__ = ["positive_int", "nonnegative_int", "positive_float", "device_name", "DEVICE_FORMS", "stderr_without"]

DEVICE_FORMS = "cpu, cuda, cuda:N"
_DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")


def _number(text: str, kind, ok, what: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if not ok(value):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    return _number(text, int, lambda v: v >= 1, "an integer >= 1")


def nonnegative_int(text: str) -> int:
    return _number(text, int, lambda v: v >= 0, "an integer >= 0")


def positive_float(text: str) -> float:
    return _number(text, float, lambda v: math.isfinite(v) and v > 0, "a finite number > 0")


def device_name(text: str) -> str:
    """A device's spelling (cpu, cuda, cuda:N), checked before anything is imported; whether this
    machine has it is `runtime.device_error`'s to say, once Warp is loaded."""
    if not _DEVICE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a device; allowed: {DEVICE_FORMS}")
    return text


def add_verbose_flag(parser) -> None:
    """`--verbose`: Warp's own messages (banner, module loads) back on."""
    parser.add_argument("--verbose", action="store_true", help="show Warp's messages (banner, kernel module loads)")


@contextmanager
def stderr_without(*needles: str):
    """Inside the block, lines written to file descriptor 2 (by Python or by native code: Warp's
    driver probe, Ray's start-up) that contain one of `needles` are dropped; the rest are passed on
    when the block ends. For notices a user of this command cannot act on."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            rest = [ln for ln in caught.read().decode(errors="replace").splitlines(True)
                    if not any(n in ln for n in needles)]
            if rest:
                sys.stderr.write("".join(rest))
