"""Families of procedural objects with a front: 15 kinds (birds, mammals, a frog, a fish, a robot,
a chair, a car, a teapot), each a builder with a body colour and optional accessories (a hat, a
scarf), and a default set of named objects built from them (``WORLD``: caption -> builder).

Conventions as the six assets of ``library`` (which stay as they are): world +Z up, the front at
+X (azimuth 0), fitted to a ball of radius 0.45 (``shapes.combine``), the parts that make the
front marked (``shapes.front``) and described in ``WORLD_FRONTS``. A caption is built from the
parameters: "a <colour> <kind>", then " wearing a <colour> hat" or " wearing a <colour> scarf"
(``caption``), so the captions are compositional and a later prompt matcher can take them apart.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from gdbench.assets import shapes as S

COLOURS = {
    "red": (0.82, 0.1, 0.08),
    "orange": (0.95, 0.5, 0.1),
    "yellow": (0.97, 0.82, 0.12),
    "green": (0.2, 0.62, 0.18),
    "blue": (0.15, 0.35, 0.8),
    "purple": (0.5, 0.2, 0.65),
    "pink": (0.95, 0.6, 0.65),
    "brown": (0.5, 0.3, 0.14),
    "black": (0.09, 0.09, 0.1),
    "white": (0.95, 0.95, 0.92),
    "grey": (0.55, 0.55, 0.57),
}
"""The colour names captions use, and their RGB."""

EYE, PUPIL, NOSE, BEAK = (0.97, 0.97, 0.95), (0.04, 0.04, 0.05), (0.12, 0.08, 0.08), (0.96, 0.55, 0.08)


def _shade(rgb, f: float):
    """``rgb`` darker (f < 1) or lighter (f > 1, towards white)."""
    if f <= 1:
        return tuple(c * f for c in rgb)
    return tuple(c + (1 - c) * (f - 1) for c in rgb)


def _coat(rgb, seed: int):
    return S.mottled(rgb, 0.08, 30, seed)


def _eyes(x: float, y: float, z: float, r: float, *, iris=EYE, pupil=PUPIL) -> list:
    """Two eyes facing +X at (x, +-y, z): a white (or coloured) ball with a pupil in front."""
    out = []
    for s in (1, -1):
        out.append(S.front(S.ellipsoid((x, s * y, z), (r * 0.7, r, r), S.solid(iris))))
        out.append(S.front(S.ellipsoid((x + 0.6 * r, s * y, z), (r * 0.35, r * 0.5, r * 0.55), S.solid(pupil))))
    return out


def _hat(top, colour) -> list:
    """A party hat on the point ``top`` (a head's top), striped with white."""
    x, y, z = top
    return [S.cone((x, y, z - 0.01), 0.08, 0.18, S.stripes(colour, COLOURS["white"], 2, 0.04))]


def _scarf(centre, radius: float, colour) -> list:
    """A scarf: a flat ring round the neck at ``centre`` and a tail hanging at the back."""
    x, y, z = centre
    ring = S.ellipsoid((x, y, z), (radius, radius, 0.035), S.stripes(colour, _shade(colour, 0.6), 0, 0.04))
    tail = S.box((x - radius * 0.8, y + radius * 0.5, z - 0.07), (0.03, 0.06, 0.14), S.solid(colour))
    return [ring, tail]


# ------------------------------------------------------------------------------ birds
def chick(rgb, hat=None, scarf=None):
    parts = [
        S.ellipsoid((0, 0, 0), (0.22, 0.2, 0.19), _coat(rgb, 21)),
        S.ellipsoid((0.12, 0, 0.22), (0.13, 0.13, 0.13), _coat(rgb, 22)),  # head
        S.front(S.cone((0.23, 0, 0.21), 0.035, 0.09, S.solid(BEAK), rotate=("y", 90))),  # beak
        *_eyes(0.22, 0.06, 0.27, 0.025, iris=PUPIL),
        S.ellipsoid((-0.02, 0.19, 0.02), (0.13, 0.04, 0.08), _coat(_shade(rgb, 0.85), 23)),  # wings
        S.ellipsoid((-0.02, -0.19, 0.02), (0.13, 0.04, 0.08), _coat(_shade(rgb, 0.85), 23)),
        S.ellipsoid((0.08, 0.07, -0.19), (0.07, 0.035, 0.02), S.solid(BEAK)),  # feet
        S.ellipsoid((0.08, -0.07, -0.19), (0.07, 0.035, 0.02), S.solid(BEAK)),
    ]
    return _dress(parts, (0.12, 0, 0.35), (0.1, 0, 0.12), 0.15, hat, scarf)


def owl(rgb, hat=None, scarf=None):
    face = _shade(rgb, 1.6)
    parts = [
        S.ellipsoid((0, 0, 0), (0.19, 0.2, 0.3), _coat(rgb, 31)),
        S.front(S.ellipsoid((0.12, 0, 0.14), (0.07, 0.17, 0.13), S.solid(face))),  # facial disc
        S.front(S.ellipsoid((0.1, 0, -0.05), (0.1, 0.14, 0.16), S.spots(face, _shade(rgb, 0.8), 0.02, 40, 0.4, 32))),
        *_eyes(0.18, 0.07, 0.16, 0.05, iris=(0.98, 0.78, 0.1)),
        S.front(S.cone((0.2, 0, 0.1), 0.025, 0.07, S.solid((0.35, 0.3, 0.25)), rotate=("y", 120))),  # beak
        S.cone((0.02, 0.12, 0.25), 0.05, 0.12, _coat(rgb, 33), rotate=("x", -20)),  # ear tufts
        S.cone((0.02, -0.12, 0.25), 0.05, 0.12, _coat(rgb, 33), rotate=("x", 20)),
        S.ellipsoid((-0.02, 0.19, -0.02), (0.12, 0.04, 0.22), _coat(_shade(rgb, 0.75), 34)),  # wings
        S.ellipsoid((-0.02, -0.19, -0.02), (0.12, 0.04, 0.22), _coat(_shade(rgb, 0.75), 34)),
        S.ellipsoid((0.08, 0.07, -0.3), (0.06, 0.04, 0.02), S.solid((0.9, 0.7, 0.2))),  # feet
        S.ellipsoid((0.08, -0.07, -0.3), (0.06, 0.04, 0.02), S.solid((0.9, 0.7, 0.2))),
    ]
    return _dress(parts, (0.02, 0, 0.33), (0.02, 0, 0.2), 0.19, hat, scarf)


def duck(rgb, hat=None, scarf=None):
    wing = _shade(rgb, 0.85)
    parts = [
        S.ellipsoid((0, 0, 0), (0.32, 0.24, 0.2), _coat(rgb, 41)),
        S.ellipsoid((-0.3, 0, 0.1), (0.1, 0.08, 0.06), S.solid(rgb), rotate=("y", 30)),  # tail
        S.ellipsoid((0.2, 0, 0.25), (0.15, 0.14, 0.15), _coat(rgb, 42)),  # head
        S.front(S.ellipsoid((0.38, 0, 0.22), (0.09, 0.07, 0.03), S.solid(BEAK))),  # beak
        *_eyes(0.31, 0.08, 0.3, 0.035, iris=PUPIL),
        S.ellipsoid((-0.02, 0.21, 0.04), (0.16, 0.06, 0.09), S.stripes(rgb, wing, 0, 0.05)),  # wings
        S.ellipsoid((-0.02, -0.21, 0.04), (0.16, 0.06, 0.09), S.stripes(rgb, wing, 0, 0.05)),
    ]
    return _dress(parts, (0.2, 0, 0.4), (0.18, 0, 0.13), 0.13, hat, scarf)


def bird(rgb, hat=None, scarf=None):
    belly = _shade(rgb, 1.5)
    parts = [
        S.ellipsoid((0, 0, 0), (0.24, 0.13, 0.14), _coat(rgb, 51), rotate=("y", -10)),
        S.front(S.ellipsoid((0.08, 0, -0.04), (0.14, 0.1, 0.1), S.solid(belly))),  # breast
        S.ellipsoid((0.2, 0, 0.13), (0.1, 0.09, 0.09), _coat(rgb, 52)),  # head
        S.front(S.cone((0.28, 0, 0.12), 0.025, 0.08, S.solid((0.2, 0.18, 0.15)), rotate=("y", 95))),  # beak
        *_eyes(0.27, 0.05, 0.16, 0.02, iris=PUPIL),
        S.box((-0.3, 0, 0.06), (0.18, 0.1, 0.02), S.solid(_shade(rgb, 0.7)), rotate=("y", -20)),  # tail
        S.ellipsoid((-0.02, 0.12, 0.03), (0.15, 0.03, 0.07), _coat(_shade(rgb, 0.75), 53)),  # wings
        S.ellipsoid((-0.02, -0.12, 0.03), (0.15, 0.03, 0.07), _coat(_shade(rgb, 0.75), 53)),
        S.cylinder((0.04, 0.04, -0.16), 0.008, 0.08, S.solid((0.3, 0.25, 0.2))),  # legs
        S.cylinder((0.04, -0.04, -0.16), 0.008, 0.08, S.solid((0.3, 0.25, 0.2))),
    ]
    return _dress(parts, (0.2, 0, 0.22), (0.16, 0, 0.06), 0.1, hat, scarf)


# ------------------------------------------------------------------------------ mammals
def _quadruped(rgb, seed: int, *, head_z: float = 0.14, legs: float = 0.14, body=(0.28, 0.13, 0.12)):
    """Body, head and four legs of a four-legged animal facing +X; its face goes on the head."""
    coat = _coat(rgb, seed)
    z = -body[2] - legs / 2 + 0.03
    return [
        S.ellipsoid((0, 0, 0), body, coat),
        S.ellipsoid((body[0], 0, head_z), (0.12, 0.12, 0.11), coat),  # head
        *[S.cylinder((x, y, z), 0.04, legs, coat) for x in (0.17, -0.17) for y in (0.08, -0.08)],
    ]


def cat(rgb, hat=None, scarf=None):
    inner = (0.95, 0.65, 0.7)
    parts = _quadruped(rgb, 61) + [
        S.cone((0.27, 0.07, 0.22), 0.045, 0.09, _coat(rgb, 62), rotate=("x", -10)),  # ears
        S.cone((0.27, -0.07, 0.22), 0.045, 0.09, _coat(rgb, 62), rotate=("x", 10)),
        S.front(S.ellipsoid((0.3, 0.07, 0.24), (0.01, 0.025, 0.04), S.solid(inner))),  # inside the ears
        S.front(S.ellipsoid((0.3, -0.07, 0.24), (0.01, 0.025, 0.04), S.solid(inner))),
        *_eyes(0.37, 0.045, 0.17, 0.025, iris=(0.55, 0.8, 0.2)),
        S.front(S.ellipsoid((0.4, 0, 0.13), (0.015, 0.02, 0.012), S.solid(inner))),  # nose
        S.front(S.ellipsoid((0.39, 0, 0.105), (0.02, 0.035, 0.02), S.solid(_shade(rgb, 1.5)))),  # muzzle
        S.cylinder((-0.33, 0, 0.12), 0.02, 0.26, _coat(rgb, 63), rotate=("y", -35)),  # tail
    ]
    return _dress(parts, (0.28, 0, 0.25), (0.25, 0, 0.06), 0.1, hat, scarf)


def _contrast(rgb, f: float = 1.45):
    """A lighter shade of a dark colour, a tan for a light one (a muzzle that shows)."""
    return _shade(rgb, f) if sum(rgb) / 3 < 0.6 else (0.82, 0.62, 0.42)


def dog(rgb, hat=None, scarf=None):
    ear = _shade(rgb, 0.6)
    parts = _quadruped(rgb, 71, legs=0.16) + [
        S.front(S.ellipsoid((0.4, 0, 0.1), (0.08, 0.06, 0.05), S.solid(_contrast(rgb)))),  # muzzle
        S.front(S.ellipsoid((0.48, 0, 0.12), (0.02, 0.025, 0.02), S.solid(NOSE))),  # nose
        *_eyes(0.37, 0.05, 0.18, 0.022, iris=PUPIL),
        S.ellipsoid((0.25, 0.12, 0.12), (0.04, 0.02, 0.08), S.solid(ear), rotate=("x", 15)),  # floppy ears
        S.ellipsoid((0.25, -0.12, 0.12), (0.04, 0.02, 0.08), S.solid(ear), rotate=("x", -15)),
        S.front(S.ellipsoid((0.44, 0, 0.05), (0.02, 0.025, 0.01), S.solid((0.9, 0.45, 0.5)))),  # tongue
        S.cylinder((-0.31, 0, 0.1), 0.02, 0.16, _coat(rgb, 72), rotate=("y", -45)),  # tail
    ]
    return _dress(parts, (0.28, 0, 0.25), (0.25, 0, 0.06), 0.1, hat, scarf)


def pig(rgb, hat=None, scarf=None):
    snout = _shade(rgb, 0.55)
    parts = _quadruped(rgb, 81, head_z=0.06, legs=0.1, body=(0.3, 0.18, 0.17)) + [
        S.front(S.cylinder((0.43, 0, 0.05), 0.055, 0.05, S.solid(snout), rotate=("y", 90))),  # snout
        S.front(S.ellipsoid((0.456, 0.022, 0.05), (0.01, 0.014, 0.02), S.solid(NOSE))),  # nostrils
        S.front(S.ellipsoid((0.456, -0.022, 0.05), (0.01, 0.014, 0.02), S.solid(NOSE))),
        *_eyes(0.39, 0.06, 0.11, 0.02, iris=PUPIL),
        S.cone((0.3, 0.08, 0.15), 0.04, 0.07, S.solid(snout), rotate=("y", 40)),  # ears, tipped forward
        S.cone((0.3, -0.08, 0.15), 0.04, 0.07, S.solid(snout), rotate=("y", 40)),
        S.ellipsoid((-0.31, 0, 0.05), (0.03, 0.03, 0.03), S.solid(snout)),  # tail
    ]
    return _dress(parts, (0.3, 0, 0.17), (0.22, 0, 0.03), 0.14, hat, scarf)


def bear(rgb, hat=None, scarf=None):
    light = _shade(rgb, 1.45)
    coat = _coat(rgb, 91)
    parts = [
        S.ellipsoid((0, 0, -0.08), (0.2, 0.2, 0.22), coat),  # sitting body
        S.front(S.ellipsoid((0.1, 0, -0.1), (0.12, 0.14, 0.15), S.solid(light))),  # belly
        S.ellipsoid((0.04, 0, 0.22), (0.14, 0.14, 0.13), coat),  # head
        S.ellipsoid((0.02, 0.11, 0.33), (0.04, 0.05, 0.05), coat),  # round ears
        S.ellipsoid((0.02, -0.11, 0.33), (0.04, 0.05, 0.05), coat),
        S.front(S.ellipsoid((0.16, 0, 0.18), (0.05, 0.06, 0.045), S.solid(light))),  # muzzle
        S.front(S.ellipsoid((0.21, 0, 0.2), (0.02, 0.025, 0.018), S.solid(NOSE))),  # nose
        *_eyes(0.16, 0.055, 0.26, 0.02, iris=PUPIL),
        S.ellipsoid((0.08, 0.2, -0.02), (0.06, 0.05, 0.12), coat, rotate=("y", -30)),  # arms
        S.ellipsoid((0.08, -0.2, -0.02), (0.06, 0.05, 0.12), coat, rotate=("y", -30)),
        S.ellipsoid((0.15, 0.11, -0.27), (0.12, 0.06, 0.06), coat),  # legs, forward
        S.ellipsoid((0.15, -0.11, -0.27), (0.12, 0.06, 0.06), coat),
    ]
    return _dress(parts, (0.04, 0, 0.35), (0.03, 0, 0.11), 0.15, hat, scarf)


def rabbit(rgb, hat=None, scarf=None):
    inner, coat = (0.95, 0.65, 0.7), _coat(rgb, 101)
    parts = [
        S.ellipsoid((0, 0, -0.05), (0.2, 0.17, 0.2), coat),  # body
        S.ellipsoid((0.1, 0, 0.2), (0.12, 0.11, 0.11), coat),  # head
        S.ellipsoid((0.06, 0.05, 0.4), (0.03, 0.045, 0.14), coat, rotate=("x", -8)),  # long ears
        S.ellipsoid((0.06, -0.05, 0.4), (0.03, 0.045, 0.14), coat, rotate=("x", 8)),
        S.front(S.ellipsoid((0.085, 0.05, 0.4), (0.01, 0.025, 0.1), S.solid(inner), rotate=("x", -8))),
        S.front(S.ellipsoid((0.085, -0.05, 0.4), (0.01, 0.025, 0.1), S.solid(inner), rotate=("x", 8))),
        *_eyes(0.2, 0.055, 0.24, 0.022, iris=PUPIL),
        S.front(S.ellipsoid((0.22, 0, 0.18), (0.015, 0.02, 0.015), S.solid(inner))),  # nose
        S.ellipsoid((-0.21, 0, -0.08), (0.06, 0.06, 0.06), S.solid(COLOURS["white"])),  # tail
        S.ellipsoid((0.12, 0.09, -0.24), (0.1, 0.05, 0.03), coat),  # feet
        S.ellipsoid((0.12, -0.09, -0.24), (0.1, 0.05, 0.03), coat),
    ]
    return _dress(parts, (0.1, 0, 0.31), (0.08, 0, 0.1), 0.12, hat, scarf)


def frog(rgb, hat=None, scarf=None):
    coat = S.spots(rgb, _shade(rgb, 0.6), 0.02, 40, 0.4, 111)
    belly = _shade(rgb, 1.6)
    parts = [
        S.ellipsoid((0, 0, 0), (0.26, 0.24, 0.12), coat),
        S.ellipsoid((0.04, 0, -0.04), (0.22, 0.2, 0.08), S.solid(belly)),
        S.ellipsoid((0.14, 0.1, 0.11), (0.06, 0.06, 0.06), coat),  # eye bulges
        S.ellipsoid((0.14, -0.1, 0.11), (0.06, 0.06, 0.06), coat),
        *_eyes(0.18, 0.1, 0.13, 0.035, iris=(0.98, 0.85, 0.2)),
        S.front(S.box((0.24, 0, 0.0), (0.02, 0.24, 0.012), S.solid(_shade(rgb, 0.35)))),  # mouth
        S.ellipsoid((-0.12, 0.23, -0.08), (0.14, 0.06, 0.05), coat),  # hind legs
        S.ellipsoid((-0.12, -0.23, -0.08), (0.14, 0.06, 0.05), coat),
        S.ellipsoid((0.2, 0.14, -0.1), (0.06, 0.05, 0.03), S.solid(belly)),  # front feet
        S.ellipsoid((0.2, -0.14, -0.1), (0.06, 0.05, 0.03), S.solid(belly)),
    ]
    return _dress(parts, (0.05, 0, 0.12), (0.1, 0, 0.02), 0.18, hat, scarf)


def fish(rgb, hat=None, scarf=None):
    coat = S.stripes(rgb, _shade(rgb, 1.5), 0, 0.07)
    fin = S.solid(_shade(rgb, 0.7))
    parts = [
        S.ellipsoid((0, 0, 0), (0.3, 0.08, 0.16), coat),
        S.cone((-0.32, 0, 0), 0.13, 0.16, fin, rotate=("y", 90)),  # tail fin (apex towards the body)
        S.box((-0.02, 0, 0.17), (0.18, 0.015, 0.06), fin, rotate=("y", 15)),  # dorsal fin
        S.box((0.05, 0.08, -0.06), (0.08, 0.01, 0.04), fin, rotate=("x", 30)),  # side fins
        S.box((0.05, -0.08, -0.06), (0.08, 0.01, 0.04), fin, rotate=("x", -30)),
        S.front(S.ellipsoid((0.25, 0, -0.01), (0.06, 0.07, 0.11), S.solid(_contrast(rgb, 1.6)))),  # pale face
        *_eyes(0.22, 0.055, 0.04, 0.035),
        S.front(S.ellipsoid((0.3, 0, -0.02), (0.015, 0.035, 0.015), S.solid(_shade(rgb, 0.3)))),  # mouth
    ]
    return _dress(parts, (0.12, 0, 0.15), (0.15, 0, 0.0), 0.12, hat, scarf)


# ------------------------------------------------------------------------------ things
def robot(rgb, hat=None, scarf=None):
    metal, dark = S.mottled(rgb, 0.1, 20, 121), S.solid((0.15, 0.15, 0.17))
    parts = [
        S.box((0, 0, 0), (0.2, 0.26, 0.26), metal),  # body
        S.front(S.box((0.1, 0, 0.02), (0.01, 0.14, 0.12), S.checker((0.2, 0.8, 0.9), (0.1, 0.3, 0.4), 0.03))),
        S.box((0, 0, 0.23), (0.18, 0.2, 0.15), metal),  # head
        *_eyes(0.09, 0.05, 0.25, 0.025, iris=(0.3, 0.95, 0.95)),
        S.front(S.box((0.092, 0, 0.19), (0.01, 0.1, 0.02), S.stripes((0.1, 0.1, 0.1), EYE, 1, 0.02))),
        S.cylinder((0, 0, 0.35), 0.01, 0.08, dark),  # antenna
        S.ellipsoid((0, 0, 0.4), (0.025, 0.025, 0.025), S.solid((0.95, 0.2, 0.2))),
        S.cylinder((0, 0.16, 0.02), 0.035, 0.22, metal),  # arms
        S.cylinder((0, -0.16, 0.02), 0.035, 0.22, metal),
        S.box((0, 0.07, -0.22), (0.1, 0.08, 0.18), dark),  # legs
        S.box((0, -0.07, -0.22), (0.1, 0.08, 0.18), dark),
        S.box((0.03, 0.07, -0.32), (0.16, 0.09, 0.03), metal),  # feet
        S.box((0.03, -0.07, -0.32), (0.16, 0.09, 0.03), metal),
    ]
    return _dress(parts, (0, 0, 0.31), (0, 0, 0.15), 0.14, hat, scarf)


def chair(rgb, hat=None, scarf=None):
    wood = S.mottled((0.45, 0.28, 0.12), 0.2, 60, 131)
    cushion = S.checker(rgb, _shade(rgb, 1.4), 0.05)
    legs = [S.cylinder((x, y, -0.2), 0.02, 0.3, wood) for x in (0.16, -0.16) for y in (0.16, -0.16)]
    parts = [
        S.box((0, 0, -0.03), (0.38, 0.38, 0.05), wood),  # seat
        S.front(S.box((0.01, 0, 0.005), (0.34, 0.34, 0.03), cushion)),  # seat cushion
        S.box((-0.17, 0, 0.2), (0.04, 0.38, 0.42), wood),  # back rest (at -X: the front faces +X)
        S.box((-0.145, 0, 0.22), (0.01, 0.3, 0.32), S.solid(rgb)),  # its padding, facing the seat
        *legs,
    ]
    return _dress(parts, (-0.17, 0, 0.42), (-0.17, 0, 0.3), 0.06, hat, scarf)


def car(rgb, hat=None, scarf=None):
    paint, glass, tyre = S.mottled(rgb, 0.06, 25, 141), S.solid((0.55, 0.75, 0.9)), S.solid((0.08, 0.08, 0.08))
    wheels = [S.cylinder((x, y, -0.1), 0.08, 0.05, tyre, rotate=("x", 90)) for x in (0.2, -0.2) for y in (0.15, -0.15)]
    parts = [
        S.box((0, 0, -0.04), (0.6, 0.28, 0.12), paint),  # body
        S.box((-0.04, 0, 0.08), (0.3, 0.24, 0.12), paint),  # cabin
        S.front(S.box((0.115, 0, 0.08), (0.01, 0.2, 0.09), glass, rotate=("y", -25))),  # windscreen
        S.box((-0.195, 0, 0.08), (0.01, 0.2, 0.08), glass),  # rear window
        S.front(S.ellipsoid((0.3, 0.09, -0.03), (0.01, 0.035, 0.025), S.solid((0.98, 0.95, 0.7)))),  # headlights
        S.front(S.ellipsoid((0.3, -0.09, -0.03), (0.01, 0.035, 0.025), S.solid((0.98, 0.95, 0.7)))),
        S.front(S.box((0.301, 0, -0.06), (0.01, 0.1, 0.03), S.stripes((0.2, 0.2, 0.2), (0.7, 0.7, 0.7), 1, 0.02))),
        S.box((-0.301, 0.09, -0.03), (0.01, 0.05, 0.02), S.solid((0.9, 0.05, 0.05))),  # tail lights
        S.box((-0.301, -0.09, -0.03), (0.01, 0.05, 0.02), S.solid((0.9, 0.05, 0.05))),
        *wheels,
    ]
    return _dress(parts, (-0.04, 0, 0.14), (-0.04, 0, 0.1), 0.1, hat, scarf)


def teapot(rgb, hat=None, scarf=None):
    glaze = S.mottled(rgb, 0.05, 20, 151)
    decal = S.spots((0.95, 0.72, 0.15), (0.8, 0.2, 0.2), 0.02, 25, 0.4, 152)
    handle = [
        S.ellipsoid((-0.26 - 0.06 * math.sin(a), 0, 0.02 + 0.1 * math.cos(a)), (0.025, 0.025, 0.03), S.solid(rgb))
        for a in (k * math.pi / 6 for k in range(7))
    ]
    parts = [
        S.ellipsoid((0, 0, 0), (0.24, 0.24, 0.18), glaze),
        S.front(S.cylinder((0.28, 0, 0.04), 0.03, 0.2, glaze, rotate=("y", 55))),  # spout
        S.front(S.ellipsoid((0.355, 0, 0.1), (0.02, 0.035, 0.02), S.solid(_shade(rgb, 0.6)))),  # its opening
        S.front(S.ellipsoid((0.2, 0, -0.02), (0.06, 0.12, 0.09), decal)),  # a painted flower on the front
        S.ellipsoid((0, 0, 0.17), (0.12, 0.12, 0.04), S.solid(_shade(rgb, 0.85))),  # lid
        S.ellipsoid((0, 0, 0.22), (0.03, 0.03, 0.03), S.solid(_shade(rgb, 0.6))),  # knob
        S.cylinder((0, 0, -0.17), 0.14, 0.03, S.solid(_shade(rgb, 0.85))),  # foot
        *handle,
    ]
    return _dress(parts, (0, 0, 0.24), (0, 0, -0.1), 0.22, hat, scarf)


def _dress(parts: list, top, neck, neck_radius: float, hat, scarf):
    """``parts`` with a hat on ``top`` and a scarf round ``neck`` (colour names or None), combined."""
    if hat is not None:
        parts = parts + _hat(top, COLOURS[hat])
    if scarf is not None:
        parts = parts + _scarf(neck, neck_radius, COLOURS[scarf])
    return S.combine(parts)


KINDS: dict[str, tuple[Callable, str]] = {
    "chick": (chick, "the eyes and the orange beak"),
    "owl": (owl, "the facial disc, the big eyes and the beak"),
    "duck": (duck, "the eyes and the orange beak"),
    "bird": (bird, "the pale breast, the eyes and the beak"),
    "cat": (cat, "the face: eyes, nose, muzzle and the inside of the ears"),
    "dog": (dog, "the face: eyes, muzzle, nose and tongue"),
    "pig": (pig, "the face: the snout with its nostrils, and the eyes"),
    "bear": (bear, "the face and the pale belly"),
    "rabbit": (rabbit, "the face and the pink inside of the ears"),
    "frog": (frog, "the eyes and the wide mouth"),
    "fish": (fish, "the pale face, the eyes and the mouth"),
    "robot": (robot, "the eyes, the mouth grille and the chest panel"),
    "chair": (chair, "the seat's cushion, the back rest behind it"),
    "car": (car, "the windscreen, headlights and grille"),
    "teapot": (teapot, "the spout and the flower painted under it"),
}
"""Kind -> (builder, what its front shows)."""


@dataclass(frozen=True)
class Spec:
    """One object: a kind, its colour and optional accessories (colour names of ``COLOURS``)."""

    kind: str
    colour: str
    hat: str | None = None
    scarf: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {self.kind!r}")
        for name in ("colour", "hat", "scarf"):
            v = getattr(self, name)
            if (v is not None or name == "colour") and v not in COLOURS:
                raise ValueError(f"{name}: expected one of {', '.join(COLOURS)}, got {v!r}")
        if self.hat is not None and self.scarf is not None:
            raise ValueError("hat, scarf: one accessory per object")

    @property
    def caption(self) -> str:
        article = "an" if self.colour[0] in "aeiou" else "a"
        base = f"{article} {self.colour} {self.kind}"
        if self.hat is not None:
            return f"{base} wearing a {self.hat} hat"
        if self.scarf is not None:
            return f"{base} wearing a {self.scarf} scarf"
        return base

    def build(self):
        return KINDS[self.kind][0](COLOURS[self.colour], hat=self.hat, scarf=self.scarf)


DEFAULT_SET: tuple[Spec, ...] = (
    Spec("chick", "yellow"), Spec("chick", "yellow", hat="red"),
    Spec("owl", "brown"), Spec("owl", "white"),
    Spec("duck", "white"), Spec("duck", "blue"),
    Spec("bird", "red"), Spec("bird", "blue"),
    Spec("cat", "orange"), Spec("cat", "black"), Spec("cat", "grey", scarf="red"),
    Spec("dog", "brown"), Spec("dog", "white", scarf="blue"),
    Spec("pig", "pink"), Spec("pig", "pink", hat="blue"),
    Spec("bear", "brown"), Spec("bear", "white"),
    Spec("rabbit", "grey"), Spec("rabbit", "white"),
    Spec("frog", "green"), Spec("frog", "red"),
    Spec("fish", "orange"), Spec("fish", "blue"),
    Spec("robot", "grey"), Spec("robot", "red", hat="yellow"),
    Spec("chair", "red"), Spec("chair", "green"),
    Spec("car", "red"), Spec("car", "blue"), Spec("car", "yellow"),
    Spec("teapot", "white"), Spec("teapot", "blue"),
)  # fmt: skip
"""The named objects of the world, in a fixed order (committed captions)."""

WORLD: dict[str, Spec] = {s.caption: s for s in DEFAULT_SET}
"""Caption -> spec of every object of the default set."""

WORLD_FRONTS: dict[str, str] = {c: KINDS[s.kind][1] for c, s in WORLD.items()}
"""Caption -> what its front shows (every object of the set has one)."""
