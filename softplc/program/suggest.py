"""Suggestions ("did you mean 'x'?") for misspelt names: places, symbols, keys, channels, plants.

Owns: how close a name must be to count as a likely misspelling, and the hint's wording.
Does not know: where the names come from.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping

# SequenceMatcher ratio at or above which a known name is offered (difflib's default): catches
# one or two wrong, missing or swapped letters (`s1_in` -> `s1_i`, `colour` -> `coloured`)
# without offering unrelated names.
CUTOFF = 0.6

# Keys other Petri-net and PLC tools use for what is spelt differently here; no spelling is
# close to them, so difflib alone would not help.
KEY_ALIASES = {
    "guard": "when",
    "condition": "when",
    "if": "when",
    "action": "do",
    "actions": "do",
    "pre": "from",
    "inputs": "from",
    "post": "to",
    "marking": "tokens",
    "initial": "tokens",
    "test": "read",
    "inhibitor": "inhibit",
    "time": "duration",
    "symbols_file": "io_image",
    "io": "io_image",
}


def closest(word: str, choices: Iterable[str], aliases: Mapping[str, str] | None = None
            ) -> str | None:
    """The known name most like `word` (or its alias, if known), None when none is close."""
    known = sorted({str(c) for c in choices if str(c) != word})
    if aliases and aliases.get(word) in known:
        return aliases[word]
    same = [k for k in known if k.lower() == word.lower()]  # `REAL` for `real`: IEC's spelling
    if same:
        return same[0]
    found = difflib.get_close_matches(word, known, n=1, cutoff=CUTOFF)
    return found[0] if found else None


def did_you_mean(word: object, choices: Iterable[str]) -> str:
    """` (did you mean 'x'?)` for the closest known name, or "" when none is close."""
    best = closest(str(word), choices)
    return f" (did you mean {best!r}?)" if best is not None else ""


def did_you_mean_key(word: object, choices: Iterable[str]) -> str:
    """As did_you_mean, for a YAML key: also offers the key other tools' names stand for."""
    best = closest(str(word), choices, KEY_ALIASES)
    return f" (did you mean {best!r}?)" if best is not None else ""
