"""Text read from and written into the files a user gives and gets: numbers read strictly, TOML
strings and comments written so that any name survives them.

- :func:`decimal`: a number of a file or an option, as a person writes it in ASCII (``-1.5``,
  ``2e-3``, ``.5``). Python's ``float()`` also takes ``"0_5"`` (5.0: a tenfold mass from a
  typo), ``"nan"``, ``"infinity"``, and Arabic-Indic or full-width digits; none of them is a
  number a robot's file should hold.
- :func:`number_argument`, :func:`whole_argument`: the argparse types of every numeric
  option of the command-line tools (``type=float`` and ``type=int`` take the same typos).
- :func:`toml_string`: a TOML basic string (``"..."``) of any text, in ASCII: the quotation
  mark, the backslash, every control character (TOML refuses C0 and DEL raw) and every other
  character escaped. Every writer of TOML text goes through it.
- :func:`comment`: a name as it may stand in a TOML or XML comment, on one line
  (:func:`cochlea.errors.printable`), with nothing a comment cannot hold.
"""

from __future__ import annotations

import argparse
import math
import re

from .errors import printable

#: A decimal number in ASCII: optional sign, digits with an optional point (or a point and
#: digits), an optional exponent. No underscores, no other scripts' digits, no nan or inf.
DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
#: A whole number in ASCII, optionally signed.
INTEGER = re.compile(r"[+-]?[0-9]+")


def decimal(text: str) -> float | None:
    """``text`` (surrounding white space allowed) as a float if it is a plain decimal number,
    else None. The value may still overflow to inf (``1e999``): callers check finiteness."""
    text = text.strip(" \t\r\n")
    if not DECIMAL.fullmatch(text):
        return None
    return float(text)


def integer(text: str) -> int | None:
    """``text`` as an int if it is plain ASCII digits (optionally signed, at most 18 of them),
    else None."""
    text = text.strip(" \t\r\n")
    if not INTEGER.fullmatch(text) or len(text.lstrip("+-")) > 18:
        return None
    return int(text)


def strict_float(text: str) -> float:
    """:func:`decimal`, finite, or ValueError (where ``float()`` was: a parser's ``try``)."""
    value = decimal(text)
    if value is None or not math.isfinite(value):
        raise ValueError(f"not a plain finite decimal number: {comment(text)!r}")
    return value


def strict_int(text: str) -> int:
    """:func:`integer`, or ValueError (where ``int()`` was)."""
    value = integer(text)
    if value is None:
        raise ValueError(f"not a plain whole number: {comment(text)!r}")
    return value


def number_argument(text: str) -> float:
    """argparse type of a number option: a plain decimal (:func:`decimal`) and finite, else
    argparse's one-line refusal (exit 2): ``--force-N 0_5`` is not 5 N, ``--speed-mm-s nan``
    no speed. Ranges are the option's own checks."""
    value = decimal(text)
    if value is None or not math.isfinite(value):
        raise argparse.ArgumentTypeError(
            f"{comment(text)!r}: expected a plain decimal number, e.g. 0.5, -2 or 1e-3")
    return value


def whole_argument(text: str) -> int:
    """argparse type of a whole-number option: plain ASCII digits, optionally signed
    (:func:`integer`), else argparse's one-line refusal (exit 2)."""
    value = integer(text)
    if value is None:
        raise argparse.ArgumentTypeError(f"{comment(text)!r}: expected a whole number, e.g. 3")
    return value


_TOML_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
                 "\r": "\\r"}


def _escape(ch: str) -> str:
    code = ord(ch)
    if ch in _TOML_ESCAPES:
        return _TOML_ESCAPES[ch]
    if 0x20 <= code < 0x7f:
        return ch
    if 0xd800 <= code <= 0xdfff:
        raise ValueError(f"{comment(ch)!r} is a byte that is not UTF-8: a TOML file cannot "
                         "name it")
    return f"\\u{code:04x}" if code <= 0xffff else f"\\U{code:08x}"


def toml_string(text: str) -> str:
    """``text`` as a TOML basic string, quotes included, in ASCII: ``it's "x"`` ->
    ``"it's \\"x\\""``; every control character (C0, DEL, C1) and every character beyond
    ASCII as ``\\uXXXX`` (``\\UXXXXXXXX`` beyond the BMP, where JSON's surrogate pair is no
    TOML). For text without DEL or characters beyond the BMP, the same as ``json.dumps``.
    Raises ValueError for a lone surrogate (a file name's byte that is not UTF-8, as Python
    carries it): no TOML string can hold one."""
    return '"' + "".join(_escape(ch) for ch in text) + '"'


def comment(text: str, xml: bool = False) -> str:
    """``text`` fit for a comment line of a TOML file (or, ``xml``, inside an XML comment):
    control characters as ``\\xNN`` (one line; TOML and XML refuse them raw), a lone
    surrogate as ``\\udcNN``; with ``xml``, ``--`` (which an XML comment may not hold) as
    ``-\\x2d``."""
    out = printable(text).encode("utf-8", "backslashreplace").decode("utf-8")
    return out.replace("--", "-\\x2d") if xml else out
