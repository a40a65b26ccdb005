"""Argument types shared by the subcommands: each turns bad text into argparse's one-line error
(exit status 2) naming the value."""

from __future__ import annotations

import argparse
import math


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be >= 0 and finite, got {text}")
    return value


def positive_int(text: str) -> int:
    """A whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def size_wxh(text: str) -> tuple[int, int]:
    """'WxH' (width first, as image sizes are written) -> (H, W), rows first as arrays are."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH (e.g. 64x64), got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be at least 1x1, got {text!r}")
    return h, w


def window_ps(text: str) -> tuple[float, float]:
    """'START:STOP' in ps after the laser sync, 0 <= START < STOP."""
    parts = text.split(":")
    try:
        start, stop = (float(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP in ps, got {text!r}") from None
    if not (math.isfinite(start) and math.isfinite(stop) and stop > start >= 0):
        raise argparse.ArgumentTypeError(f"window needs 0 <= START < STOP, got {text!r}")
    return start, stop
