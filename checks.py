"""The one idiom for checking what a caller gives a public entry point: each function returns the value in checked form
or raises ValueError naming it, with what was found and what was expected ("window: expected an integer in 20..500
samples, found 200.5"). Ranges are written as text: "a..b" integers, "[a, b]", "(a, b]", "[a, b)", "(a, b)" reals."""
from __future__ import annotations

import argparse
import math
import numbers
import os

import numpy as np


def _interval(text):
    """(lo, hi, lo_open, hi_open, integer) of a range text; 'inf' reads as math.inf."""
    if ".." in text:
        lo, hi = text.split("..")
        return float(lo), float(hi), False, False, True
    lo, hi = text[1:-1].split(",")
    return float(lo), float(hi), text[0] == "(", text[-1] == ")", False


def _within(x, lo, hi, lo_open, hi_open):
    """Whether x lies in the range and is finite (NaN compares False; a huge int is compared exactly)."""
    return (x > lo if lo_open else x >= lo) and (x < hi if hi_open else x <= hi) and -math.inf < x < math.inf


def _expected(interval, unit, integer, what=None):
    kind = what or ("an integer" if integer else "a number")
    return f"{kind} in {interval}{' ' + unit if unit else ''}"


def number(name, value, interval="(-inf, inf)", unit="", what=None):
    """value as an int ("a..b") or a float, finite and within the interval; bool, None, text and complex refused."""
    lo, hi, lo_open, hi_open, integer = _interval(interval)
    kinds = numbers.Integral if integer else numbers.Real
    if not (isinstance(value, kinds) and not isinstance(value, (bool, np.bool_)) and
            _within(value, lo, hi, lo_open, hi_open)):
        raise ValueError(f"{name}: expected {_expected(interval, unit, integer, what)}, found {value!r:.40}")
    return int(value) if integer else float(value)


def flag(name, value):
    """value as a bool: True or False (numbers and text refused)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, found {value!r:.40}")
    return bool(value)


def choice(name, value, options):
    """value, one of options."""
    if not isinstance(value, str) or value not in options:
        raise ValueError(f"{name}: expected one of {', '.join(map(repr, options))}, found {value!r:.40}")
    return value


def array(name, value, shape, interval="(-inf, inf)", unit=""):
    """value as a float array of `shape` (None in it: any length >= 1), every entry finite and within the interval
    ("a..b": integers); bool, complex, text and object entries refused."""
    lo, hi, lo_open, hi_open, integer = _interval(interval)
    a = np.asarray(None) if (r := real_array(value)) is None else r
    want = f"{'integers' if integer else 'numbers'} in {interval}{' ' + unit if unit else ''}, shape {_shape(shape)}"
    if a.dtype.kind not in ("iu" if integer else "iuf"):
        raise ValueError(f"{name}: expected {want}, found {kind(value)}")
    if a.ndim != len(shape) or any(s is not None and s != k or k == 0 for s, k in zip(shape, a.shape)):
        raise ValueError(f"{name}: expected {want}, found shape {a.shape}")
    bad = ~(np.isfinite(a) & (a > lo if lo_open else a >= lo) & (a < hi if hi_open else a <= hi))
    if bad.any():
        i = tuple(int(k) for k in np.argwhere(bad)[0])
        raise ValueError(f"{name}: expected {want}, found {a[i].item()!r} at index {i if len(i) != 1 else i[0]}")
    return a.astype(int if integer else float)


def floats(name, value, shape):
    """value as a finite float array of exactly `shape`, for the 1 kHz loop: a float64 array passes in about 1 us;
    anything else is checked in full (array)."""
    if type(value) is np.ndarray and value.shape == shape and value.dtype == np.float64 and \
            math.isfinite(value.sum()):
        return value                                   # (inf - inf sums to NaN: one sum screens every entry)
    return array(name, value, shape)


def _shape(shape):
    return "(" + ", ".join("n" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def real_array(value):
    """value as a numpy array of real numbers (ints or floats, not cast), or None: bool, complex, text, objects, ragged
    nesting (which np.asarray(x, dtype=float) would cast silently, drop the imaginary part of, or fail on)."""
    try:
        a = np.asarray(value) if not isinstance(value, (str, bytes)) else None
    except (TypeError, ValueError):
        return None
    return a if a is not None and a.dtype.kind in "iuf" else None


def real(name, value):
    """value as a float array of any shape (checked no further) of real numbers; bool, complex, text refused."""
    if (a := real_array(value)) is None:
        raise ValueError(f"{name}: expected real numbers, found {kind(value)}")
    return a.astype(float)


def kind(value):
    """What value is, for an error message: "complex values (list)", "ragged nesting (list)", "'abc'", "None"."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return f"ragged nesting ({type(value).__name__})"
    names = {"b": "bool", "c": "complex", "O": "non-numeric", "U": "text", "S": "text"}
    if a.dtype.kind in names:
        return f"{names[a.dtype.kind]} values ({type(value).__name__})" if a.ndim else f"{value!r:.40}"
    return f"{value!r:.40}"


def generator(name, value):
    """value, a np.random.Generator (the only source of randomness)."""
    if not isinstance(value, np.random.Generator):
        raise ValueError(f"{name}: expected a np.random.Generator (np.random.default_rng(seed)), found "
                         f"{type(value).__name__} {value!r:.40}")
    return value


def has_methods(name, value, *methods):
    """value, an object with these callable methods (duck typing: what the caller will call on it)."""
    missing = [m for m in methods if not callable(getattr(value, m, None))]
    if missing:
        raise ValueError(f"{name}: expected an object with {', '.join(m + '()' for m in methods)}, found "
                         f"{type(value).__name__} {value!r:.60} without {', '.join(missing)}")
    return value


def instance(name, value, cls):
    """value, an instance of cls."""
    if not isinstance(value, cls):
        raise ValueError(f"{name}: expected an instance of {cls.__name__}, found {type(value).__name__} {value!r:.60}")
    return value


def output_file(name, path):
    """path (text) of a file to write, whose folder exists and is writable: checked before any work starts."""
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise ValueError(f"{name}: expected a file path, found {path!r}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder) or not os.access(folder, os.W_OK) or os.path.isdir(path):
        why = "is a folder" if os.path.isdir(path) else f"its folder {folder} does not exist or is not writable"
        raise ValueError(f"{name}: expected a file path to write, found {str(path)!r} ({why})")
    return str(path)


class Parser(argparse.ArgumentParser):
    """argparse's parser whose every refusal is one line on stderr (exit status 2): what was wrong, not the usage."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (--help lists the arguments)\n")


def argument(interval, unit=""):
    """An argparse type: the text as a number within the interval (see number), else argparse's one-line error."""
    integer = _interval(interval)[4]

    def parse(text):
        try:
            value = int(text) if integer else float(text)
            return number("value", value, interval, unit)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {_expected(interval, unit, integer)}, found {text!r}") from None
    parse.__name__ = "integer" if integer else "number"
    return parse


def writable(text):
    """An argparse type: a file path whose folder exists and is writable."""
    try:
        return output_file("path", text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).split(": ", 1)[1]) from None
