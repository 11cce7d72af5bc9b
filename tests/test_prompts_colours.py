"""Prompts against their assets on the committed prompt sets, the colour table and its categories,
and the bank's encoding."""

from pathlib import Path

import torch

from gdbench.priors.empirical import EmpiricalPrior
from gdbench.priors.text import CaptionMatcher


def _prompt_set(name: str) -> list[tuple[str, str]]:
    path = Path(__file__).resolve().parents[1] / "fixtures" / "prompts" / name
    rows = [line.rstrip("\n").split("\t") for line in path.read_text().splitlines() if not line.startswith("#")]
    return [(p, w) for p, w in rows]


def test_prompts_that_contradict_their_asset_are_refused_on_the_committed_sets():
    """fixtures/prompts: 62 paraphrases that must be accepted and matched to their caption, and
    56 prompts naming another colour (crimson, azure, lavender ... judged against the asset's
    own surface colours), a second object or a negation, which must be refused. The rates are
    the ones docs/reliability.md reports: 1 false refusal ('a tan and white corgi': XKCD's tan is
    a pale yellow-brown, the corgi's coat an orange one) and no false acceptance."""
    from gdbench.assets.library import ASSETS
    from gdbench.priors.prompt_check import contradiction

    m = CaptionMatcher(sorted(ASSETS))

    def verdict(prompt):
        try:
            caption, _ = m.match_scored(prompt)
        except ValueError:
            return None, "no match"
        return caption, contradiction(prompt, caption, m)

    match, contradict = _prompt_set("match.tsv"), _prompt_set("contradict.tsv")
    assert len(match) >= 50 and len(contradict) >= 50
    assert {w for _, w in contradict} == {"colour", "object", "negation"}
    false_refusals = [p for p, want in match if verdict(p) != (want, None)]
    false_accepts = [p for p, _ in contradict if verdict(p)[1] is None]
    assert false_refusals == ["a tan and white corgi"], false_refusals
    assert false_accepts == [], false_accepts


def test_the_shipped_colour_table_is_matplotlibs():
    """Oracle: matplotlib's CSS4 and XKCD tables and ``to_rgb``, as the lexicon was built from them
    before it was shipped as data (so that a prompt check imports no matplotlib); the basic terms'
    prototypes are XKCD's values."""
    import subprocess
    import sys

    import numpy as np
    from matplotlib import colors as mc

    from gdbench.priors import colour_names
    from gdbench.priors import prompt_check as pc

    assert colour_names.parse() == colour_names.from_matplotlib() and len(colour_names.parse()) > 1000
    table = dict(mc.CSS4_COLORS) | {k.removeprefix("xkcd:"): v for k, v in mc.XKCD_COLORS.items()}
    want = {}
    for name, value in table.items():
        if "/" not in name and not any(ch.isdigit() for ch in name):
            want[tuple(name.replace("'", "").split())] = mc.to_rgb(value)
    want = dict(sorted(want.items(), key=lambda kv: -len(kv[0])))
    assert list(pc.colour_lexicon().items()) == list(want.items())
    basic = pc._lab(np.array([mc.to_rgb(f"xkcd:{b}") for b in pc.BASIC]))
    assert np.array_equal(pc._basic_lab(), basic)
    code = "import sys; from gdbench.priors import prompt_check as pc; pc.colour_lexicon(); pc._basic_lab(); "
    code += "print('matplotlib' in sys.modules)"
    root = __import__("pathlib").Path(__file__).resolve().parents[1]
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root)
    assert run.returncode == 0 and run.stdout == "False\n", run.stderr[-2000:]


def test_colour_categories_of_the_basic_terms_and_of_known_names():
    """Each of the eleven basic colour terms' own centroid falls in its category, and named colours
    outside them fall where a dictionary puts them."""
    import numpy as np

    from gdbench.priors import prompt_check as pc

    lex = pc.colour_lexicon()

    def cat(name):
        return pc.BASIC[int(pc.category(pc._lab(np.array(lex[tuple(name.split())]))))]

    assert [cat(b) for b in pc.BASIC] == list(pc.BASIC)
    known = {"crimson": "red", "scarlet": "red", "azure": "blue", "navy blue": "blue", "lavender": "purple"}
    known |= {"lime green": "green", "chocolate": "brown", "charcoal": "black", "magenta": "pink"}
    assert {k: cat(k) for k in known} == known


def test_palette_category_over_distinct_colours_equals_every_face_its_own():
    import numpy as np

    from gdbench.priors import prompt_check as pc

    pc._palette_category.cache_clear()
    for caption in ("a yellow duck", "a hamburger"):
        lab = pc.palette(caption)[0]
        got = pc._palette_category(caption)
        assert len(np.unique(lab, axis=0)) < len(lab) // 4  # faces share colours: the distinct ones are fewer
        np.testing.assert_array_equal(got, pc.category(lab))  # the oracle: each face on its own
        assert len(set(got.tolist())) >= 2 and not got.flags.writeable


def test_encode_maps_the_bank_to_minus_one_one_as_images_times_two_minus_one():
    from gdbench.assets.bank import load_bank

    bank = load_bank("a yellow duck", EmpiricalPrior().bank_config)
    expected = bank.images * 2 - 1  # the oracle: the plain expression's bits
    prior = EmpiricalPrior()
    cond = prior.encode("a yellow duck")
    assert torch.equal(cond.images, expected)
    # the bank is left as it was: a second encode gives the same images, in a tensor of its own
    again = prior.encode("a yellow duck").images
    assert torch.equal(again, expected) and again.data_ptr() != cond.images.data_ptr()
    for name in ("depth", "azimuth", "elevation", "alpha"):
        assert torch.equal(getattr(cond, name), getattr(bank, name))
    assert torch.equal(cond.variant, torch.zeros(len(bank)))
