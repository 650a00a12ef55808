"""``cochlea.text``: numbers read strictly, and the one TOML string writer every tool that
writes TOML (descriptions, starter and excitation scenarios, sweep samples, tuned.toml, fits)
goes through: any text reads back the same, in an ASCII file."""

from __future__ import annotations

import json
import tomllib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cochlea.text import comment, decimal, integer, toml_string

#: Every code point but the lone surrogates (which no UTF-8 file holds).
TEXT = st.text(st.characters(blacklist_categories=("Cs",)), max_size=40)


@given(TEXT)
def test_any_text_reads_back_from_its_toml_string(text):
    written = toml_string(text)
    assert written.isascii() and "\n" not in written
    assert tomllib.loads(f"k = {written}")["k"] == text


@pytest.mark.parametrize("text", ["it's.toml", 'a"b', "back\\slash", "del\x7f", "esc\x1b[31m",
                                  "new\nline", "nul\x00", "c1\x9b", "smile\U0001F600",
                                  "bras articul\u00e9", "tab\t"])
def test_awkward_names_read_back(text):
    """json.dumps, which two writers used, writes DEL raw and a character beyond the BMP as a
    surrogate pair, both invalid TOML; a hand-written '"{x}"' broke on the quote."""
    assert tomllib.loads(f"k = {toml_string(text)}")["k"] == text
    if "\x7f" not in text and "\U0001F600" not in text:
        assert toml_string(text) == json.dumps(text)  # unchanged where JSON's was right


def test_a_lone_surrogate_is_refused():
    with pytest.raises(ValueError, match="not UTF-8"):
        toml_string("bad\udce9.toml")


def test_a_comment_is_one_line_and_safe_in_xml():
    assert comment("a\nb\x1b\x7f--c\udce9") == "a\\x0ab\\x1b\\x7f--c\\udce9"
    assert "--" not in comment("x--y---z", xml=True)


@pytest.mark.parametrize("text, value", [("1", 1.0), ("-2.5", -2.5), ("+.5", 0.5), ("3.", 3.0),
                                         ("1e-3", 1e-3), (" 7E+2 ", 700.0)])
def test_plain_decimals_are_read(text, value):
    assert decimal(text) == value


@pytest.mark.parametrize("text", ["0_5", "1_000", "nan", "inf", "-Infinity", "\u0660.\u0665",
                                  "\uff10.\uff15", "0x10", "1e", ".", "", "1 2", "\u00bd"])
def test_what_float_reads_but_a_file_should_not_hold_is_refused(text):
    assert decimal(text) is None


def test_integers_are_ascii_digits():
    assert integer(" 12 ") == 12 and integer("-3") == -3
    assert integer("1_0") is None and integer("\u0661") is None and integer("1.0") is None
