"""The kinds of object the catalogue's captions name ("duck", "lego figure", ...), the words that
name them (their names, plurals and ``SYNONYMS``) and the accessories a world object can wear: the
vocabulary ``compose`` matches prompts with and ``prompt_check`` finds second objects with."""

from __future__ import annotations

import functools

SYNONYMS = {
    "burger": "hamburger", "cheeseburger": "hamburger", "couch": "sofa", "settee": "sofa",
    "lego": "lego figure", "minifigure": "lego figure", "minifig": "lego figure",
    "puppy": "dog", "kitten": "cat", "kitty": "cat", "bunny": "rabbit", "duckling": "duck",
    "chicken": "chick", "automobile": "car", "armchair": "chair", "toad": "frog", "goldfish": "fish",
    "android": "robot", "kettle": "teapot", "piglet": "pig", "teddy": "bear",
}  # fmt: skip
"""Words that name a kind of the catalogue by another name."""
BROADER = {"corgi": "dog"}
"""Kind -> the kind it is a sort of: "a corgi dog" names the corgi, not a dog of the world set."""
ACCESSORIES = {
    "hat": "hat", "cap": "hat", "beanie": "hat", "bonnet": "hat", "party hat": "hat", "top hat": "hat",
    "scarf": "scarf", "muffler": "scarf", "shawl": "scarf",
}  # fmt: skip
"""Words for what the world's objects can wear, and which accessory each is."""


def kind_of(caption: str) -> str | None:
    """The kind of a catalogue caption ("a pink pig wearing a blue hat" -> "pig"), None for others."""
    from gdbench.assets.library import PARTS

    return PARTS[caption][0] if caption in PARTS else None


@functools.cache
def kind_words() -> dict[tuple[str, ...], str]:
    """Word tuples (longest first) -> kind: every kind's name, its plural and ``SYNONYMS``."""
    from gdbench.assets.library import PARTS

    out = {}
    for kind, *_ in PARTS.values():
        out[tuple(kind.split())] = kind
        out[tuple((kind + "s").split())] = kind
    for word, kind in SYNONYMS.items():
        out[(word,)] = kind
        out[(word + "s",)] = kind
    return dict(sorted(out.items(), key=lambda kv: -len(kv[0])))


def _find(words: list[str], table: dict[tuple[str, ...], str]) -> list[tuple[int, int, str]]:
    """(start, end, value) of the table's phrases in ``words``, longest first, each word used once."""
    used: set[int] = set()
    found = []
    for phrase, value in table.items():
        n = len(phrase)
        for i in range(len(words) - n + 1):
            if tuple(words[i : i + n]) == phrase and not used & set(range(i, i + n)):
                found.append((i, i + n, value))
                used |= set(range(i, i + n))
    return sorted(found)


def kinds_named(text: str) -> set[str]:
    """The kinds a piece of (``prompt_check._words``-normalised) text names, the most specific of
    each family ("corgi dog" -> {"corgi"})."""
    kinds = {k for _, _, k in _find(text.split(), kind_words())}
    return {k for k in kinds if not any(BROADER.get(o) == k for o in kinds)}


def accessories_named(text: str) -> set[str]:
    table = {tuple(w.split()): a for w, a in sorted(ACCESSORIES.items(), key=lambda kv: -len(kv[0].split()))}
    return {a for _, _, a in _find(text.split(), table)}
