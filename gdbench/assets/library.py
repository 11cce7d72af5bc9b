"""The paper's six prompts as procedural meshes: a corgi, a yellow duck, a hamburger, a Lego
figure, a penguin and a sofa. World +Z is up and each asset's front faces +X (azimuth 0),
so a result with its front on more than one side (the multi-face problem) can be detected.
Each mesh fits in a ball of radius 0.45 around the origin.

The catalogue a prompt can name is these six (``ASSETS``, the default prompt set of sweeps,
set-up and the shipped learned prior) and the world's objects (``families.WORLD``): ``CAPTIONS``,
``build``, ``FRONTS`` and ``PARTS`` cover both."""

from __future__ import annotations

import functools
from collections.abc import Callable

from gdbench.assets import shapes as S
from gdbench.assets.families import WORLD, WORLD_FRONTS

WHITE, BLACK = (0.96, 0.96, 0.94), (0.05, 0.05, 0.06)


def yellow_duck():
    yellow, orange = (0.98, 0.82, 0.12), (0.95, 0.45, 0.08)
    return S.combine(
        [
            S.ellipsoid((0, 0, 0), (0.32, 0.24, 0.2), S.mottled(yellow, 0.1, 30, 1)),
            S.ellipsoid((-0.3, 0, 0.1), (0.1, 0.08, 0.06), S.solid(yellow), rotate=("y", 30)),  # tail
            S.ellipsoid((0.2, 0, 0.25), (0.15, 0.14, 0.15), S.mottled(yellow, 0.1, 30, 2)),  # head
            S.front(S.ellipsoid((0.38, 0, 0.22), (0.09, 0.07, 0.03), S.solid(orange))),  # beak
            S.front(S.ellipsoid((0.3, 0.08, 0.3), (0.03, 0.03, 0.035), S.solid(BLACK))),
            S.front(S.ellipsoid((0.3, -0.08, 0.3), (0.03, 0.03, 0.035), S.solid(BLACK))),
            S.ellipsoid((-0.02, 0.21, 0.04), (0.16, 0.06, 0.09), S.stripes(yellow, (0.9, 0.66, 0.1), 0, 0.05)),  # wing
            S.ellipsoid((-0.02, -0.21, 0.04), (0.16, 0.06, 0.09), S.stripes(yellow, (0.9, 0.66, 0.1), 0, 0.05)),
        ]
    )


def corgi():
    tan, white, pink = (0.85, 0.52, 0.22), WHITE, (0.9, 0.5, 0.55)
    coat = S.spots(tan, (0.7, 0.4, 0.15), radius=0.03, count=60, seed=3)
    legs = [S.cylinder((x, y, -0.16), 0.045, 0.14, S.solid(white)) for x in (0.17, -0.17) for y in (0.09, -0.09)]
    return S.combine(
        [
            S.ellipsoid((0, 0, 0), (0.3, 0.14, 0.12), coat),
            S.ellipsoid((0.05, 0, -0.06), (0.22, 0.1, 0.07), S.solid(white)),  # belly
            S.ellipsoid((0.3, 0, 0.12), (0.12, 0.11, 0.1), coat),  # head
            S.front(S.ellipsoid((0.4, 0, 0.08), (0.07, 0.06, 0.05), S.solid(white))),  # muzzle
            S.front(S.ellipsoid((0.47, 0, 0.1), (0.02, 0.025, 0.02), S.solid(BLACK))),  # nose
            S.front(S.ellipsoid((0.38, 0.05, 0.16), (0.02, 0.02, 0.02), S.solid(BLACK))),
            S.front(S.ellipsoid((0.38, -0.05, 0.16), (0.02, 0.02, 0.02), S.solid(BLACK))),
            S.cone((0.28, 0.07, 0.2), 0.05, 0.12, S.solid(tan), rotate=("x", -20)),  # ears
            S.cone((0.28, -0.07, 0.2), 0.05, 0.12, S.solid(tan), rotate=("x", 20)),
            S.front(S.ellipsoid((0.44, 0, 0.03), (0.02, 0.03, 0.01), S.solid(pink))),  # tongue
            S.ellipsoid((-0.31, 0, 0.06), (0.05, 0.04, 0.04), S.solid(white)),  # tail
            *legs,
        ]
    )


def hamburger():
    bun, sesame = (0.86, 0.56, 0.22), (0.98, 0.94, 0.8)
    top = S.spots(bun, sesame, radius=0.018, count=70, extent=0.35, seed=5)
    return S.combine(
        [
            S.ellipsoid((0, 0, 0.12), (0.3, 0.3, 0.13), top),
            S.cylinder((0, 0, 0.02), 0.31, 0.03, S.mottled((0.3, 0.7, 0.15), 0.3, 40, 6)),  # lettuce
            S.box((0, 0, -0.01), (0.46, 0.46, 0.02), S.solid((0.98, 0.75, 0.1)), rotate=("z", 45)),  # cheese
            S.cylinder((0, 0, -0.06), 0.29, 0.08, S.mottled((0.35, 0.18, 0.08), 0.3, 50, 7)),  # patty
            S.cylinder((0, 0, -0.11), 0.27, 0.025, S.checker((0.85, 0.1, 0.08), (0.7, 0.08, 0.05), 0.05)),  # tomato
            S.cylinder((0, 0, -0.17), 0.3, 0.08, S.mottled(bun, 0.1, 30, 8)),  # bottom bun
            S.cylinder((0.16, 0, 0.3), 0.008, 0.24, S.solid((0.85, 0.75, 0.55))),  # toothpick
            S.box((0.24, 0, 0.38), (0.16, 0.006, 0.09), S.stripes((0.9, 0.1, 0.1), WHITE, 0, 0.03)),  # front flag
            # the front (+X): a pickle slice sticking out and a ketchup drip, so the burger has a front
            S.cylinder((0.3, 0, 0.0), 0.07, 0.02, S.spots((0.35, 0.55, 0.15), (0.75, 0.8, 0.4), 0.012, 20, 0.4, 13)),
            S.ellipsoid((0.29, 0.0, -0.09), (0.03, 0.09, 0.05), S.solid((0.8, 0.05, 0.03))),
            S.ellipsoid((0.27, 0.09, -0.12), (0.025, 0.03, 0.06), S.solid((0.8, 0.05, 0.03))),
        ]
    )


def lego_figure():
    yellow, red, blue = (0.98, 0.8, 0.08), (0.8, 0.08, 0.08), (0.1, 0.25, 0.7)
    return S.combine(
        [
            S.cylinder((0, 0, 0.33), 0.09, 0.13, S.solid(yellow)),  # head
            S.cylinder((0, 0, 0.41), 0.05, 0.04, S.solid(yellow)),  # stud
            S.front(S.ellipsoid((0.085, 0.035, 0.35), (0.01, 0.012, 0.018), S.solid(BLACK))),  # eyes
            S.front(S.ellipsoid((0.085, -0.035, 0.35), (0.01, 0.012, 0.018), S.solid(BLACK))),
            S.front(S.box((0.087, 0, 0.305), (0.01, 0.07, 0.012), S.solid(BLACK))),  # mouth
            S.box((0, 0, 0.15), (0.16, 0.26, 0.22), S.solid(red)),  # torso
            S.front(S.box((0.082, 0, 0.17), (0.01, 0.12, 0.12), S.checker(WHITE, (0.1, 0.5, 0.1), 0.03))),  # print
            S.cylinder((0, 0.16, 0.14), 0.04, 0.2, S.solid(red), rotate=("x", 10)),  # arms
            S.cylinder((0, -0.16, 0.14), 0.04, 0.2, S.solid(red), rotate=("x", -10)),
            S.ellipsoid((0.03, 0.17, 0.02), (0.035, 0.035, 0.035), S.solid(yellow)),  # hands
            S.ellipsoid((0.03, -0.17, 0.02), (0.035, 0.035, 0.035), S.solid(yellow)),
            S.box((0, 0, 0.02), (0.16, 0.26, 0.05), S.solid((0.2, 0.2, 0.2))),  # hips
            S.box((0, 0.065, -0.15), (0.15, 0.12, 0.3), S.solid(blue)),  # legs
            S.box((0, -0.065, -0.15), (0.15, 0.12, 0.3), S.solid(blue)),
            S.box((0.03, 0, -0.3), (0.2, 0.26, 0.03), S.solid(blue)),  # feet
        ]
    )


def penguin():
    orange = (0.98, 0.55, 0.1)
    back = S.mottled((0.08, 0.09, 0.12), 0.5, 35, 9)
    return S.combine(
        [
            S.ellipsoid((0, 0, 0), (0.2, 0.19, 0.3), back),
            S.front(
                S.ellipsoid((0.07, 0, -0.03), (0.15, 0.15, 0.25), S.spots(WHITE, (0.85, 0.85, 0.8), 0.02, 30, 0.4, 10))
            ),
            S.ellipsoid((0.02, 0, 0.32), (0.13, 0.13, 0.12), back),  # head
            S.front(S.ellipsoid((0.1, 0.05, 0.35), (0.03, 0.03, 0.03), S.solid(WHITE))),
            S.front(S.ellipsoid((0.1, -0.05, 0.35), (0.03, 0.03, 0.03), S.solid(WHITE))),
            S.front(S.ellipsoid((0.125, 0.055, 0.355), (0.012, 0.012, 0.012), S.solid(BLACK))),
            S.front(S.ellipsoid((0.125, -0.055, 0.355), (0.012, 0.012, 0.012), S.solid(BLACK))),
            S.front(S.cone((0.13, 0, 0.3), 0.03, 0.09, S.solid(orange), rotate=("y", 100))),  # beak
            S.ellipsoid((0.0, 0.2, 0.0), (0.05, 0.03, 0.18), back, rotate=("x", -15)),  # flippers
            S.ellipsoid((0.0, -0.2, 0.0), (0.05, 0.03, 0.18), back, rotate=("x", 15)),
            S.ellipsoid((0.08, 0.07, -0.3), (0.08, 0.04, 0.02), S.solid(orange)),  # feet
            S.ellipsoid((0.08, -0.07, -0.3), (0.08, 0.04, 0.02), S.solid(orange)),
        ]
    )


def sofa():
    fabric = S.stripes((0.2, 0.35, 0.65), (0.28, 0.45, 0.78), 1, 0.05)
    wood = S.mottled((0.45, 0.28, 0.12), 0.2, 60, 11)
    cushion = S.checker((0.85, 0.3, 0.2), (0.95, 0.75, 0.2), 0.05)
    legs = [S.cylinder((x, y, -0.16), 0.02, 0.06, wood) for x in (0.15, -0.15) for y in (0.35, -0.35)]
    return S.combine(
        [
            S.box((0, 0, -0.07), (0.4, 0.8, 0.12), fabric),  # seat
            S.box((-0.16, 0, 0.08), (0.1, 0.8, 0.3), fabric),  # back rest (at -X: front faces +X)
            S.box((0, 0.37, 0.0), (0.42, 0.08, 0.2), fabric),  # arm rests
            S.box((0, -0.37, 0.0), (0.42, 0.08, 0.2), fabric),
            S.front(S.box((0.04, 0.17, 0.0), (0.3, 0.32, 0.05), cushion)),  # seat cushions
            S.front(S.box((0.04, -0.17, 0.0), (0.3, 0.32, 0.05), cushion)),
            S.front(
                S.box(
                    (-0.09, 0, 0.12), (0.05, 0.3, 0.16), S.spots((0.95, 0.9, 0.8), (0.8, 0.2, 0.3), 0.03, 25, 0.5, 12)
                )
            ),
            *legs,
        ]
    )


ASSETS: dict[str, Callable] = {
    "a corgi": corgi,
    "a yellow duck": yellow_duck,
    "a hamburger": hamburger,
    "a lego figure": lego_figure,
    "a penguin": penguin,
    "a sofa": sofa,
}
"""Captions (the paper's prompts) to mesh builders, written out by hand."""

CAPTIONS: tuple[str, ...] = (*sorted(ASSETS), *WORLD)
"""Every caption of the catalogue: the six, then the world's objects in their committed order."""

PARTS: dict[str, tuple[str, str | None, str | None, str | None]] = {
    "a corgi": ("corgi", None, None, None),
    "a yellow duck": ("duck", "yellow", None, None),
    "a hamburger": ("hamburger", None, None, None),
    "a lego figure": ("lego figure", None, None, None),
    "a penguin": ("penguin", None, None, None),
    "a sofa": ("sofa", None, None, None),
} | {c: (s.kind, s.colour, s.hat, s.scarf) for c, s in WORLD.items()}
"""Caption -> (kind, body colour name or None, hat colour or None, scarf colour or None): what a
compositional prompt is matched on (``priors.compose``). The six have no colour in their caption
but the duck's."""


FRONTS: dict[str, str | None] = {
    "a corgi": "the face: eyes, muzzle, nose and tongue",
    "a yellow duck": "the head's eyes and orange beak",
    "a hamburger": None,
    "a lego figure": "the face printed on the head and the print on the torso",
    "a penguin": "the white belly, the eyes and the orange beak",
    "a sofa": "the seat with its cushions, the back rest behind them",
} | WORLD_FRONTS
"""What each asset shows at its front (azimuth 0, +X), or None where it has none (the hamburger is
the same from every side), then every object of the world set: the Janus classes need a front,
and assets without one are left out of the Janus claims (docs/scoring.md). The builders mark these
parts (``shapes.front``), so the metric's front test can look at them (``metrics.views.front_masks``)."""


def has_front(caption: str) -> bool:
    """Whether the asset ``caption`` declares a front (``FRONTS``)."""
    if caption not in FRONTS:
        raise ValueError(f"caption: unknown asset {caption!r}; known: {sorted(FRONTS)}")
    return FRONTS[caption] is not None


VARIANTS = 3
"""Procedural variants per caption (instance ambiguity, docs/training.md 'The embedded prior'): 0 the asset as
written above; 1 longer front to back and squat, in a warmer, darker shade; 2 compact and tall,
in a lighter shade, wearing a striped hat (the six only: a world object's hat or scarf is part of
its caption, so its variant 2 wears none it does not name). Each is the same caption (same colours by name), and
each differs from the others at every view, so a result can be matched to its instance."""


def check_caption(caption: str) -> str:
    """``caption`` if the catalogue has it, else a ValueError naming the nearest captions."""
    if caption not in PARTS:
        from difflib import get_close_matches

        near = get_close_matches(str(caption), CAPTIONS, n=3, cutoff=0.0)
        raise ValueError(
            f"caption: unknown asset {caption!r}; nearest: {', '.join(map(repr, near))} "
            f"(`gdbench prompts` lists all {len(CAPTIONS)})"
        )
    return caption


def build(caption: str, variant: int = 0):
    """The trimesh mesh (with vertex colours) of a caption of the catalogue, as variant ``variant``."""
    check_caption(caption)
    if not 0 <= variant < VARIANTS:
        raise ValueError(f"variant: expected 0..{VARIANTS - 1}, got {variant}")
    return _built(caption, variant).copy()


@functools.lru_cache(maxsize=32)
def _built(caption: str, variant: int):
    if caption in ASSETS:
        mesh = ASSETS[caption]()
        return mesh if variant == 0 else _variant(mesh, variant)
    mesh = WORLD[caption].build()
    return mesh if variant == 0 else _variant(mesh, variant, hat=False)


def _variant(mesh, variant: int, hat: bool = True):
    import numpy as np

    m = mesh.copy()
    rgb = m.visual.vertex_colors[:, :3].astype(np.float64) / 255
    if variant == 1:
        m.apply_transform(np.diag([1.3, 0.9, 0.78, 1.0]))
        rgb = rgb * np.array([0.95, 0.8, 0.7])  # warmer and darker
        parts = [m]
    else:
        m.apply_transform(np.diag([0.8, 0.95, 1.25, 1.0]))
        rgb = rgb + (1 - rgb) * 0.3  # lighter
        parts = [m]
    if variant == 2 and hat:
        top = m.vertices[np.argmax(m.vertices[:, 2])]
        cap = S.cone((top[0], top[1], top[2] - 0.01), 0.09, 0.2, S.stripes((0.2, 0.3, 0.85), WHITE, 2, 0.04))
        parts = [m, cap]
    m.visual.vertex_colors = np.concatenate([np.round(rgb * 255), np.full((len(rgb), 1), 255)], 1).astype(np.uint8)
    return S.combine(parts)
