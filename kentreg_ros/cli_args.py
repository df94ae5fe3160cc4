"""argparse value types shared by the command-line tools (replay, play)."""

from __future__ import annotations

import argparse
import math


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected an integer, got {text!r}') from None


def non_negative_int(text: str) -> int:
    """An integer >= 0, or an ``ArgumentTypeError`` naming the text."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f'expected a non-negative integer (>= 0), got {text!r}')
    return value


def positive_int(text: str) -> int:
    """An integer >= 1, or an ``ArgumentTypeError`` naming the text (also for negatives)."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'expected a positive integer (>= 1), got {text!r}')
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0, or an ``ArgumentTypeError`` naming the text."""
    value = _finite_float(text)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f'expected a finite number >= 0, got {text!r}')
    return value


def positive_float(text: str) -> float:
    """A finite number > 0, or an ``ArgumentTypeError`` naming the text."""
    value = _finite_float(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f'expected a finite number > 0, got {text!r}')
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a number, got {text!r}') from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'expected a finite number, got {text!r}')
    return value
