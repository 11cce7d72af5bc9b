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
    "android": "robot", "kettle": "teapot", "piglet": "pig", "teddy": "bear", "duckie": "duck",
    "ducky": "duck", "birdie": "bird",
}  # fmt: skip
"""Words that name a kind of the catalogue by another name."""
BROADER = {"corgi": "dog"}
"""Kind -> the kind it is a sort of: "a corgi dog" names the corgi, not a dog of the world set."""
ACCESSORIES = {
    "hat": "hat", "cap": "hat", "beanie": "hat", "bonnet": "hat", "party hat": "hat", "top hat": "hat",
    "scarf": "scarf", "muffler": "scarf", "shawl": "scarf",
}  # fmt: skip
"""Words for what the world's objects can wear, and which accessory each is."""
NOT_KINDS = ("hot dog", "hotdog", "guinea pig", "dog house", "doghouse", "fish tank", "duck billed", "sea lion",
             "birds eye", "bird s eye", "cat walk", "pig tail", "car seat", "robot vacuum")  # fmt: skip
"""Phrases that hold a kind's word but name something else ("a hot dog" is no dog)."""
REWRITES = {"polar bear": "white bear", "grizzly bear": "brown bear", "brown bear": "brown bear"}
"""Phrases that say a kind and its colour in one word."""


def plural(word: str) -> str:
    """English plural of a kind's word (duck -> ducks, bunny -> bunnies, fish -> fish)."""
    if word == "fish":
        return word
    if word.endswith("y") and word[-2:-1] not in "aeiou":
        return word[:-1] + "ies"
    return word + ("es" if word.endswith(("s", "sh", "ch", "x")) else "s")


def kind_of(caption: str) -> str | None:
    """The kind of a catalogue caption ("a pink pig wearing a blue hat" -> "pig"), None for others."""
    from gdbench.assets.library import PARTS

    return PARTS[caption][0] if caption in PARTS else None


@functools.cache
def kind_words() -> dict[tuple[str, ...], str]:
    """Word tuples (longest first) -> kind: every kind's name and ``SYNONYMS``, singular only."""
    from gdbench.assets.library import PARTS

    out = {tuple(kind.split()): kind for kind, *_ in PARTS.values()}
    out |= {(word,): kind for word, kind in SYNONYMS.items()}
    return dict(sorted(out.items(), key=lambda kv: -len(kv[0])))


@functools.cache
def plural_words() -> dict[tuple[str, ...], str]:
    """The plurals of ``kind_words`` ("ducks", "lego figures", "bunnies") -> kind."""
    out = {(*words[:-1], plural(words[-1])): kind for words, kind in kind_words().items()}
    return {w: k for w, k in out.items() if w not in kind_words()}


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


def _without(text: str, phrases) -> str:
    for p in phrases:
        text = f" {text} ".replace(f" {p} ", " ").strip()
    return text


def kinds_named(text: str) -> set[str]:
    """The kinds a piece of (``prompt_check._words``-normalised) text names, the most specific of
    each family ("corgi dog" -> {"corgi"}), plural or not; ``NOT_KINDS`` phrases and colour names
    that hold a kind's word ("duck egg blue") name none."""
    words = _without(text, (*NOT_KINDS, *_kind_colours())).split()
    kinds = {k for _, _, k in _find(words, kind_words() | plural_words())}
    return {k for k in kinds if not any(BROADER.get(o) == k for o in kinds)}


def plurals_named(text: str) -> list[str]:
    """The plural kind words in ``text`` ("two ducks" -> ["ducks"])."""
    words = _without(text, (*NOT_KINDS, *_kind_colours())).split()
    return [" ".join(words[i:j]) for i, j, _ in _find(words, plural_words()) if tuple(words[i:j]) not in kind_words()]


@functools.cache
def _kind_colours() -> tuple[str, ...]:
    """Colour names of the lexicon that hold a kind's word ("duck egg blue", "frog green")."""
    from gdbench.priors.colour_names import parse  # the lexicon's names, as prompt_check reads them

    kinds = {w for p in kind_words() for w in p}
    names = [tuple(name.replace("'", "").split()) for name in parse()]
    return tuple(" ".join(n) for n in names if len(n) > 1 and set(n) & kinds)


def accessories_named(text: str) -> set[str]:
    return {a for _, _, a in _find(text.split(), _ACCESSORY_WORDS)}


_ACCESSORY_WORDS = {tuple(w.split()): a for w, a in sorted(ACCESSORIES.items(), key=lambda kv: -len(kv[0].split()))}
"""``ACCESSORIES`` as word tuples, longest first (what ``_find`` takes)."""
