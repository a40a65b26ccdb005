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


def k_or_auto(text: str):
    """--reflectors: a whole number or 'auto' (the request checks the range)."""
    if text == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number or auto, got {text!r}") from None


def add_reflector_arguments(parser: argparse.ArgumentParser, *, as_recorded: bool = False) -> None:
    """--reflectors, --max-reflectors, --false-alarm (recon, scan, replay); ``as_recorded``: no
    defaults (a replay keeps the recording's unless given)."""
    k, kmax, fa = (None, None, None) if as_recorded else (1, 3, 1e-3)
    said = ("as recorded",) * 3 if as_recorded else ("1", "3", "1e-3")
    parser.add_argument("--reflectors", type=k_or_auto, default=k, metavar="K|auto",
                        help=f"surfaces per pixel to look for (default {said[0]}): up to K, or auto "
                             "(decided per pixel by a likelihood-ratio test, up to --max-reflectors)")
    parser.add_argument("--max-reflectors", type=positive_int, default=kmax, metavar="K",
                        help=f"--reflectors auto: most surfaces per pixel (default {said[1]})")
    parser.add_argument("--false-alarm", type=positive_float, default=fa, metavar="P",
                        help="--reflectors auto: chance per pixel and surface that background passes "
                             f"for a surface (default {said[2]})")
