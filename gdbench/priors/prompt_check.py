"""Does a prompt ask for something its matched asset is not? The embedded priors can only generate
their six assets, so a prompt that the matcher maps to one but that names another colour, a
second object or a negation must be refused, not silently trained as the caption.

The decision generalises instead of listing words:

- **Colours** are looked up in a colour-name lexicon (matplotlib's CSS4 and XKCD tables, about
  1100 names: "crimson", "azure", "lavender", "navy blue" ...) and compared with the asset's own
  surface colours (its mesh's face colours, weighted by area) in CIELAB. A colour that names the
  object ("a crimson duck") must cover at least ``DOMINANT`` of the surface within ``DELTA_E``;
  a colour in a clause about a part ("a penguin with an orange beak") at least ``PART``. So any
  colour name is judged by what the asset looks like, not by a per-asset word list.
- **A second object**: the prompt is split at coordinations ("and", "&", "plus", "next to",
  "beside"; not at commas, which list adjectives and quality tags); every part that names
  something (what is left after articles and colour names)
  must itself match the caption (the sentence model's best caption, above the matcher's
  threshold), unless it describes a depiction ("3d render", "a photo"). "A duck and a corgi" and
  "a duck next to a car" are refused; "a black and white penguin" is not.
- **Negation** is a closed grammatical class (not, no, never, without, none, nothing, neither, nor and the
  contraction n't, normalised before the words are split), so it is the one place a list is
  complete.

Measured on the committed sets ``fixtures/prompts/{match,contradict}.tsv`` by
``tests/test_priors.py``; the rates are in docs/reliability.md.
"""

from __future__ import annotations

import functools
import re

import numpy as np

DELTA_E = 15.0
"""CIELAB distance (Delta E 1976) within which a surface colour counts as the named colour."""
DOMINANT = 0.15
"""Share of the surface a colour naming the whole object must cover."""
PART = 0.004
"""Share a colour in a part clause ("with an orange beak") must cover."""

NEGATION = frozenset({"not", "no", "never", "without", "none", "nothing", "neither", "nor", "non"})
"""Negation markers, a closed class of English (after n't -> not)."""
_SPLIT = re.compile(r"\b(?:and|plus|next to|beside|besides|alongside|together with|as well as)\b|[&+]")
_PART = re.compile(r"\b(?:with|having|wearing|that has|which has)\b")
_ARTICLES = frozenset({"a", "an", "the", "of", "some", "one", "two"})
_DEPICTION = ("a 3d render", "a photo", "a drawing", "a painting", "high quality", "a 3d model", "cartoon style")


def _words(prompt: str) -> str:
    """Lower case, n't and a missing apostrophe's nt as "not", & and + as "and" and "plus", other
    punctuation as spaces."""
    t = prompt.lower().replace("n't", " not").replace("n’t", " not").replace("'", "").replace("’", "")
    t = re.sub(r"\b(is|are|was|were|do|does|did|has|have|had|ca|wo|should|could|would)nt\b", r"\1 not", t)
    t = t.replace("&", " and ").replace("+", " plus ")
    return re.sub(r"\s+", " ", re.sub(r"[^a-z0-9 ]+", " ", t)).strip()


@functools.cache
def colour_lexicon() -> dict[tuple[str, ...], tuple[float, float, float]]:
    """Colour names (as word tuples, longest first) -> sRGB in [0, 1], from matplotlib's CSS4 and
    XKCD tables (names with '/' or digits left out; XKCD's survey names win over CSS4's where both
    exist: CSS "lavender" is nearly white), as ``colour_names`` keeps them."""
    from gdbench.priors.colour_names import parse

    out = {tuple(name.replace("'", "").split()): _rgb(value) for name, value in parse().items()}
    return dict(sorted(out.items(), key=lambda kv: -len(kv[0])))


def _rgb(hex_colour: str) -> tuple[float, float, float]:
    """'#rrggbb' -> sRGB in [0, 1] (matplotlib's to_rgb, the same divisions)."""
    r, g, b = (int(hex_colour[i : i + 2], 16) / 255 for i in (1, 3, 5))
    return r, g, b


def _lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] [..., 3] -> CIELAB (D65)."""
    c = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    xyz = c @ np.array([[0.4124, 0.2126, 0.0193], [0.3576, 0.7152, 0.1192], [0.1805, 0.0722, 0.9505]])
    xyz = xyz / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


@functools.cache
def palette(caption: str) -> tuple[np.ndarray, np.ndarray]:
    """(CIELAB colours [F, 3], area weights [F] summing to 1) of the asset's surface (variant 0),
    cached on disk beside the banks (building the mesh needs trimesh's slow import)."""
    from gdbench.assets.bank import cached_arrays

    def build() -> dict[str, np.ndarray]:
        from gdbench.assets.library import build

        mesh = build(caption)
        rgb = mesh.visual.face_colors[:, :3].astype(np.float64) / 255
        return {"lab": _lab(rgb), "w": mesh.area_faces / mesh.area_faces.sum()}

    z = cached_arrays("palette", {"caption": caption}, build, version=1, fields=("lab", "w"))
    return z["lab"], z["w"]


BASIC = ("black", "white", "grey", "red", "green", "yellow", "blue", "brown", "purple", "pink", "orange")
"""Berlin and Kay's eleven basic colour terms, a closed set across languages: the categories a
named colour and the asset's surface colours are both sorted into (by the nearest of their XKCD
survey centroids)."""


@functools.cache
def _basic_lab() -> np.ndarray:
    from gdbench.priors.colour_names import parse

    table = parse()  # XKCD's values for these names (they are all in its table)
    return _lab(np.array([_rgb(table[b]) for b in BASIC]))


HUE_TOLERANCE = 45.0
"""Degrees of CIELAB hue within which a chromatic surface colour counts as the named colour."""
ACHROMATIC_CHROMA = 15.0
"""CIELAB chroma below which a colour is black, grey or white (by lightness alone)."""


def category(lab: np.ndarray) -> np.ndarray:
    """Index into ``BASIC`` of each CIELAB colour [..., 3]: below ``ACHROMATIC_CHROMA`` the basic
    achromatic term nearest in lightness, else the chromatic term nearest in hue angle plus half
    the lightness difference (which keeps brown from orange and pink from red)."""
    proto = _basic_lab()

    def hue(x):
        return np.degrees(np.arctan2(x[..., 2], x[..., 1]))

    chroma = np.hypot(lab[..., 1], lab[..., 2])
    dl = np.abs(lab[..., None, 0] - proto[:, 0])
    dh = np.abs((hue(lab)[..., None] - hue(proto) + 180) % 360 - 180)
    achromatic = np.array([b in ("black", "white", "grey") for b in BASIC])
    d = np.where(achromatic, np.inf, dh + 0.5 * dl)
    d_achromatic = np.where(achromatic, dl, np.inf)
    return np.where(chroma < ACHROMATIC_CHROMA, d_achromatic.argmin(-1), d.argmin(-1))


@functools.cache
def _palette_category(caption: str) -> np.ndarray:
    """``category`` of every colour of the asset's palette, once per asset and process instead of
    once per colour asked about: computed on its distinct colours (the duck's 163,840 faces have
    4,723) and spread back: the same values, for a fraction of the work."""
    lab = np.ascontiguousarray(palette(caption)[0])
    rows = lab.view(np.dtype((np.void, lab.itemsize * lab.shape[1]))).ravel()  # a colour's bytes as one key
    _, first, where = np.unique(rows, return_index=True, return_inverse=True)
    out = category(lab[first])[where.ravel()]
    out.flags.writeable = False  # shared by every call
    return out


def colour_share(rgb, caption: str) -> float:
    """Share of the asset's surface that is the colour ``rgb``: of its basic colour category, or
    within ``DELTA_E`` of it."""
    lab, w = palette(caption)
    c = _lab(np.asarray(rgb, dtype=np.float64))
    same = _palette_category(caption) == category(c)
    if np.hypot(c[1], c[2]) >= ACHROMATIC_CHROMA:  # and of a hue within HUE_TOLERANCE (cyan is not green)
        hue = np.degrees(np.arctan2(lab[:, 2], lab[:, 1]))
        dh = np.abs((hue - np.degrees(np.arctan2(c[2], c[1])) + 180) % 360 - 180)
        same &= dh < HUE_TOLERANCE
    near = (np.linalg.norm(lab - c, axis=-1) < DELTA_E) | same
    return float(w[near].sum())


def find_colours(text: str) -> list[str]:
    """The colour names in ``text`` (longest names first, each word used once)."""
    words = text.split()
    found, used = [], set()
    for name in colour_lexicon():
        n = len(name)
        for i in range(len(words) - n + 1):
            if tuple(words[i : i + n]) == name and not used & set(range(i, i + n)):
                found.append(" ".join(name))
                used |= set(range(i, i + n))
    return found


def contradiction(prompt: str, caption: str, matcher=None) -> str | None:
    """Why ``prompt`` asks for something the asset behind ``caption`` is not, or None.
    ``matcher`` (a CaptionMatcher over all captions) judges the parts of a coordination."""
    text = _words(prompt)
    neg = sorted(set(text.split()) & NEGATION)
    if neg:
        return f"it negates ({neg[0]!r}), and the embedded prior can only generate its assets"
    lex = colour_lexicon()
    pieces = _PART.split(text, maxsplit=1)
    head, part = pieces[0], pieces[1] if len(pieces) > 1 else ""
    for where, need in ((head, DOMINANT), (part, PART)):
        for name in find_colours(where):
            share = colour_share(lex[tuple(name.split())], caption)
            if share < need:
                kind = "the object" if need == DOMINANT else "a part"
                return (
                    f"it asks for {name} ({kind}), but {share:.0%} of that asset's surface is near {name} "
                    f"(needs {need * 100:g}%); the embedded prior has one appearance per asset"
                )
    if matcher is not None:
        parts = [p.strip() for p in _SPLIT.split(head) if p.strip()]
        named = [p for p in parts if _content(p)]
        if len(named) > 1:
            from gdbench.priors.kinds import kind_of, kinds_named

            kind = kind_of(caption)
            for p in named:
                kinds = kinds_named(p)
                if kinds:  # a part that names a kind must name the caption's
                    if kind not in kinds:
                        return f"it also names {p!r}, which is not {caption!r}; the embedded prior generates one asset"
                    continue
                scores = matcher.scores(p)
                best = max(scores, key=scores.get)
                same = best == caption or (kind is not None and kind_of(best) == kind)
                if not same or scores[best] < matcher.threshold:
                    if _is_depiction(matcher, p):
                        continue
                    return f"it also names {p!r}, which is not {caption!r}; the embedded prior generates one asset"
    return None


def colour_category_name(name: str) -> str:
    """The basic colour term (``BASIC``) a colour name of the lexicon falls in ("navy" -> "blue")."""
    rgb = colour_lexicon()[tuple(name.split())]
    return BASIC[int(category(_lab(np.asarray(rgb, dtype=np.float64))))]


def _content(part: str) -> list[str]:
    """The words of a coordination's part that name something: not articles, not colours."""
    colours = {w for name in find_colours(part) for w in name.split()}
    return [w for w in part.split() if w not in _ARTICLES and w not in colours]


def _is_depiction(matcher, part: str) -> bool:
    emb = matcher._embed([part, *_DEPICTION])
    return bool((emb[1:] @ emb[0]).max() >= 0.6)
