"""argparse value types shared by the scripts in train/: a bad value is an argparse error naming the flag."""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import tempfile
from contextlib import contextmanager

__all__ = ["positive_int", "nonnegative_int", "positive_float", "nonnegative_float", "device_name", "DEVICE_FORMS", "stderr_without",
           "add_verbose_flag", "add_device_option", "add_eager_physics_flag", "add_cache_dir_option",
           "add_eval_seed_option", "add_kmp_reference_option", "KMP_REFERENCES", "seed_error", "SEED_BITS",
           "EVAL_SEED_BITS"]

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


def nonnegative_float(text: str) -> float:
    return _number(text, float, lambda v: math.isfinite(v) and v >= 0, "a finite number >= 0")


def device_name(text: str) -> str:
    """A device's spelling (cpu, cuda, cuda:N), checked before anything is imported; whether this
    machine has it is `runtime.device_error`'s to say, once Warp is loaded."""
    if not _DEVICE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a device; allowed: {DEVICE_FORMS}")
    return text


# the seeds every command line takes: a run's or an env's (--seed, gymnasium's seed=) and the evaluation episodes'
# (--eval-seed, one integer that seeds every world: envs.vector)
SEED_BITS, EVAL_SEED_BITS = 32, 63


def seed_error(flag: str, value: int, bits: int = SEED_BITS) -> str | None:
    """The refusal of a seed outside [0, 2**bits), in one line naming the flag, or None."""
    return None if 0 <= value < 2**bits else f"{flag} {value}: must be in [0, 2**{bits})"


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


def add_device_option(parser, default: str | None = None, help: str | None = None) -> None:
    """`--device`, spelled and checked the same way by every command line (whether this machine has it:
    `runtime.device_error`, once Warp is loaded)."""
    help = help or f"{DEVICE_FORMS} (default: {default or 'cuda:0 when present, else cpu'})"
    parser.add_argument("--device", default=default, type=device_name, help=help)


def add_eager_physics_flag(parser) -> None:
    """`--eager-physics`: the physics kernels one by one, the captured graph's reference."""
    parser.add_argument("--eager-physics", action="store_true",
                        help="launch the physics kernels one by one instead of replaying one captured graph per "
                             "control step (bitwise the same results, slower: the reference)")


def add_cache_dir_option(parser) -> None:
    """`--cache-dir`: where the prepared inputs live (vkgrl_newton.cache)."""
    from pathlib import Path

    parser.add_argument("--cache-dir", type=Path, default=Path("runs/cache"),
                        help="demonstrations, KMP tables, image sets, VAEs (made on first use, reused)")


def add_eval_seed_option(parser, default: int) -> None:
    """`--eval-seed`: the evaluation episodes' seed, the same meaning in train/run.py and train/evaluate.py."""
    parser.add_argument("--eval-seed", type=int, default=default,
                        help="seeds the evaluation episodes: two policies evaluated with one eval seed (and the same "
                             "task, env, action space and worlds) see identical initial states (default %(default)s)")


KMP_REFERENCES = ("gmr", "empirical")


def add_kmp_reference_option(parser, default: str | None) -> None:
    """`--kmp-reference`: the KMP's reference distribution."""
    parser.add_argument("--kmp-reference", default=default, choices=KMP_REFERENCES,
                        help="KGRL: the KMP's reference distribution: gmr (the thesis, eqs. 4.2-4.3; default) or "
                             "empirical (the demonstrations' per-step mean and covariance: a deviation, see "
                             "docs/log/benchmarks.md); a checkpoint's own wins")
