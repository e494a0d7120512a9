"""Numbers a user gives, checked where they enter: finite, within a range, a usable seed.

Two kinds of entry use these: the command line (``number_arg``, ``integer_arg``,
``seed_arg`` are argparse ``type=`` functions; the command line prints their message as
``simulate --duration-s: nan is not a finite number; give ...``) and config
files (``check_seed``, ``check_range``; core.config refuses non-finite floats
for every field by itself).

A seed is an integer in 0 .. 2**31 - 1: what numpy's and torch's generators
and SUMO's --seed (a C int: 2**31 is "not a valid integer") all accept.

The ``MAX_*`` bounds below are shared by several modules' settings and
arguments (each says why); a bound only one module needs stays in that module.
"""

from __future__ import annotations

import argparse
import math
import numbers
from typing import Callable

from crchfl_sumo.core.errors import CrchflError

SEED_MAX = 2**31 - 1
SEED_RANGE = f"an integer in 0 .. {SEED_MAX} (2**31 - 1)"
MAX_SIMULATED_S = 86400.0  # a command simulates at most one day (its trace fills memory step by step)
MAX_DRIVE_S = 3600.0  # one drive or rendered run: an hour of simulated driving
MAX_SAMPLE_S = 3600.0  # compute time of one sample [s]: an hour (paper: 0.04 s); a shard's epoch would take months
MAX_EPOCHS = 100_000  # epochs of a training, and a federation's intervals and rounds: more runs for days at any size
MAX_SAMPLES = 10**9  # samples of a whole data set: a billion 98 KB samples fill 98 TB
MAX_RATE_BPS = 1e12  # a link's rate [bit/s]: 1 Tbit/s, above any radio or fibre link in service (800 Gbit/s)
MAX_JOBS = 1024  # processes at a time: more than any machine's cores


def range_text(lo: float, hi: float, lo_open: bool = False, hi_open: bool = False) -> str:
    """``(0, 86400]``-style text of a range; ``lo_open`` excludes ``lo``, ``hi_open`` excludes ``hi``."""
    return f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def in_range(value: float, lo: float, hi: float, lo_open: bool = False, hi_open: bool = False) -> bool:
    return (lo < value if lo_open else lo <= value) and (value < hi if hi_open else value <= hi)


def check_seed(value: object, where: str) -> int:
    """``value`` if it is a seed (0 .. 2**31 - 1); a CrchflError naming ``where`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):  # numpy integers are seeds too
        raise CrchflError(f"{where}: {value!r} is not a seed; give {SEED_RANGE}")
    if not 0 <= value <= SEED_MAX:
        raise CrchflError(f"{where}: {value} is outside the seed range; give {SEED_RANGE}")
    return int(value)


def check_range(
    value: float, where: str, lo: float, hi: float, what: str, lo_open: bool = False, inf_ok: bool = False,
    hi_open: bool = False,
) -> float:
    """``value`` if it is finite and in ``[lo, hi]`` (``lo_open``/``hi_open`` exclude an end); a CrchflError otherwise.

    ``what`` names the unit in the message: "give {what} in [lo, hi]". ``inf_ok``:
    ``inf`` passes too (a setting whose inf means "no limit"; say so in ``what``).
    """
    wanted = f"{what} in {range_text(lo, hi, lo_open, hi_open)}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise CrchflError(f"{where}: {value!r} is not a number; give {wanted}")
    if inf_ok and value == math.inf:
        return value
    if not math.isfinite(value):
        raise CrchflError(f"{where}: {value} is not a finite number; give {wanted}")
    if not in_range(value, lo, hi, lo_open, hi_open):
        raise CrchflError(f"{where}: {value:g} is out of range; give {wanted}")
    return value


# --- argparse type= functions ---------------------------------------------------------------------


def number_arg(lo: float, hi: float, what: str, lo_open: bool = False, hi_open: bool = False) -> Callable[[str], float]:
    """argparse type: a finite float in ``[lo, hi]`` (``lo_open``/``hi_open`` exclude an end); ``what`` names the unit."""
    wanted = f"{what} in {range_text(lo, hi, lo_open, hi_open)}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number; give {wanted}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} is not a finite number; give {wanted}")
        if not in_range(value, lo, hi, lo_open, hi_open):
            raise argparse.ArgumentTypeError(f"{text} is out of range; give {wanted}")
        return value

    parse.__name__ = "number"
    return parse


def auto_or(parse: Callable[[str], float]) -> Callable[[str], float | str]:
    """argparse type: "auto", or a number as ``parse`` (number_arg's) takes it."""

    def parse_auto(text: str) -> float | str:
        if text == "auto":
            return text
        try:
            return parse(text)
        except argparse.ArgumentTypeError as error:
            raise argparse.ArgumentTypeError(f"{error}, or auto") from None

    parse_auto.__name__ = parse.__name__
    return parse_auto


def integer_arg(lo: int, hi: int, what: str) -> Callable[[str], int]:
    """argparse type: an integer in ``[lo, hi]``; ``what`` as in "give {what} in 1 .. 10"."""
    wanted = f"{what} in {lo} .. {hi}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer; give {wanted}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text} is out of range; give {wanted}")
        return value

    parse.__name__ = "integer"
    return parse


def seed_arg(text: str) -> int:
    """argparse type: a seed, 0 .. 2**31 - 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed; give {SEED_RANGE}") from None
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"{text} is outside the seed range; give {SEED_RANGE}")
    return value
