"""Checked numbers, one set shared by the command lines and the library.

Each checker is an argparse ``type=``: it turns the argument's text into a number, or raises
``argparse.ArgumentTypeError`` naming the range, which argparse reports as
``error: argument --threshold: expected a number from 0 to 1, got 'nan'`` (exit status 2, no
traceback). Floats must be finite. ``checker.check(name, value)`` applies the same test to a
value passed to the library and raises ``SetupError``.
"""

from __future__ import annotations

import argparse
import math
import numbers
from typing import Optional, Union

from .errors import SetupError

Number = Union[int, float]

U32_MAX = 2**32 - 1
# Seconds that still fit the element's u64 nanosecond properties (about 584 years): far above any
# useful interval, low enough that ``seconds * 1e9`` cannot overflow.
MAX_SECONDS = 1e9


class Checked:
    """A number of type ``kind`` (int or float) in [lo, hi]; ``lo_open``: lo itself excluded.
    ``extra``: one more accepted value outside the range (the element's -1 for "from the model")."""

    def __init__(
        self,
        kind: type,
        lo: Optional[Number] = None,
        hi: Optional[Number] = None,
        *,
        lo_open: bool = False,
        extra: Optional[Number] = None,
        what: str,
    ):
        self.kind, self.lo, self.hi, self.lo_open, self.extra = kind, lo, hi, lo_open, extra
        self.what = what
        self.__name__ = what  # argparse names the type in some messages

    def ok(self, v: Number) -> bool:
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            return False
        if self.kind is int and not isinstance(v, numbers.Integral):
            return False
        if not math.isfinite(v):
            return False
        if self.extra is not None and v == self.extra:
            return True
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return self.hi is None or v <= self.hi

    def __call__(self, text: str) -> Number:
        try:
            v = self.kind(text.strip())
        except (TypeError, ValueError, OverflowError):
            v = None
        if v is None or not self.ok(v):
            raise argparse.ArgumentTypeError(f"expected {self.what}, got {text!r}")
        return v

    def check(self, name: str, value: Number) -> Number:
        """``value`` if it passes, else SetupError naming ``name`` (a library argument)."""
        if not self.ok(value):
            raise SetupError(f"{name} must be {self.what}, not {value!r}")
        return value


unit_interval = Checked(float, 0.0, 1.0, what="a number from 0 to 1")
threshold_or_model = Checked(float, 0.0, 1.0, extra=-1.0, what="-1 (from the model) or 0 to 1")
non_negative_seconds = Checked(float, 0.0, MAX_SECONDS, what=f"0 to {MAX_SECONDS:g} seconds")
positive_seconds = Checked(float, 0.0, MAX_SECONDS, lo_open=True,
                           what=f"above 0 and at most {MAX_SECONDS:g} seconds")
non_negative_int = Checked(int, 0, what="an integer, 0 or more")
positive_int = Checked(int, 1, what="an integer, 1 or more")
uint32 = Checked(int, 0, U32_MAX, what=f"an integer from 0 to {U32_MAX}")
