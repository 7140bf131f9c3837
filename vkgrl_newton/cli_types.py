"""argparse value types shared by the scripts in train/: a bad value is an argparse error naming the flag."""

from __future__ import annotations

import argparse
import math
import re

__all__ = ["positive_int", "nonnegative_int", "positive_float", "device_name", "DEVICE_FORMS"]

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
