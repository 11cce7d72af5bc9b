"""Where a scene file came from and which way is up in it: the tags gdbench writes into every
scene file, read back by every command that reads one (docs/export.md, "Up axis").

gdbench's scenes are +Z up. A file gdbench writes records its up axis and the run it holds:

- a PLY (3DGS or compressed): header comments ``gdbench run <run id>`` and ``gdbench up <axis>``;
- a ``.splat`` (a headerless format): a sidecar ``<name>.json`` beside it,
  ``{"gdbench": {"up": ..., "run": ...}}``, and ``gdbench export``'s default name says the axis
  too (``scene.y_down.splat``);
- a mesh: a ``.glb``'s glTF ``asset.extras.gdbench``, an ``.obj``'s first comment line
  ``# gdbench {"up": ..., "run": ...}`` (``app.mesh.write_mesh``).

``read_tags`` reads them back: the header or the sidecar, else the axis in an export's name
(``.y_down.``), else nothing (a file from elsewhere). ``resolve_up`` decides a command's up axis
from the file's and the one asked for, and refuses a disagreement, which would turn the scene by
the wrong rotation (a -Y-up file read as +Z up lies on its side; converted again, it is rotated
twice).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor

UpAxis = Literal["+z", "-y", "+y", "-z", "+x", "-x"]
UP_AXES: tuple[str, ...] = ("+z", "-y", "+y", "-z", "+x", "-x")
"""The up axes every command accepts (``--up``): gdbench's +z, -y (Inria / COLMAP captures and most
3DGS viewers), +y (some engines) and the other three."""

UP_NAMES = {"+z": "z_up", "-y": "y_down", "+y": "y_up", "-z": "z_down", "+x": "x_up", "-x": "x_down"}
"""The axis as ``gdbench export`` names its files: scene.y_down.ply, scene.z_up.splat, ..."""

_ROTATIONS = {
    "+z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-y": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),  # a quarter turn about +X: (x, y, z) -> (x, -z, y)
    "+y": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),  # (x, y, z) -> (x, z, -y)
    "-z": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # a half turn about +X
    "+x": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),  # a quarter turn about +Y: +Z -> +X
    "-x": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),  # +Z -> -X
}

SIDECAR_SUFFIX = ".json"
"""A .splat's tags live in ``<file>.splat.json``."""


def check_up(up, name: str = "up") -> str:
    """``up`` if it is one of ``UP_AXES``, else a ValueError naming ``name`` and the choices."""
    if not isinstance(up, str) or up not in UP_AXES:
        raise ValueError(f"{name}: expected one of {', '.join(UP_AXES)}, got {up!r}")
    return up


def up_rotation(up: str) -> Tensor:
    """The float64 [3, 3] rotation that takes gdbench's +Z-up world to one with ``up`` up: the
    smallest such rotation (about +X for the y and z axes, so +X, an asset's front, stays +X; about
    +Y for the x axes), a half turn about +X for -z."""
    return torch.tensor(_ROTATIONS[check_up(up)], dtype=torch.float64)


@dataclass(frozen=True)
class FileTags:
    """What a scene file records of itself (None: not recorded)."""

    up: str | None = None
    """The file's up axis."""
    run: str | None = None
    """The id of the run whose scene it holds."""
    source: str = ""
    """Where ``up`` was read: 'header', 'sidecar', 'name' or '' (not recorded)."""


def ply_comments(up: str, run: str | None) -> list[str]:
    """The PLY header comments that record ``up`` and ``run``."""
    return ([f"gdbench run {run}"] if run else []) + [f"gdbench up {check_up(up)}"]


def sidecar(path: str | Path) -> Path:
    """The tags file of a .splat: ``<path>.json``."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def sidecar_json(up: str, run: str | None) -> dict:
    return {"gdbench": {"up": check_up(up), "run": run}}


def _name_axis(path: Path) -> str | None:
    m = re.search(r"\.(" + "|".join(UP_NAMES.values()) + r")(?:\.|$)", path.name)
    return {v: k for k, v in UP_NAMES.items()}[m.group(1)] if m else None


def _other_tags(path: Path) -> tuple[dict, str]:
    """The tags dict of a .splat (its sidecar), .glb or .obj, and where they were ({}, '' if none)."""
    try:
        if path.suffix.lower() == ".splat":
            if not sidecar(path).is_file():
                return {}, ""
            return dict(json.loads(sidecar(path).read_text()).get("gdbench", {})), "sidecar"
        if path.suffix.lower() == ".obj":
            with open(path, encoding="utf-8", errors="replace") as f:
                for line in f:
                    if line.startswith("# gdbench "):
                        return dict(json.loads(line[len("# gdbench ") :])), "header"
                    if not line.startswith("#"):
                        break
            return {}, ""
        with open(path, "rb") as f:  # .glb: 12-byte header, then the JSON chunk (length, type, data)
            head = f.read(20)
            if head[:4] != b"glTF" or len(head) < 20:
                return {}, ""
            tree = json.loads(f.read(int.from_bytes(head[12:16], "little")))
        return dict(tree.get("asset", {}).get("extras", {}).get("gdbench", {})), "header"
    except (OSError, ValueError, TypeError, AttributeError) as e:
        where = sidecar(path) if path.suffix.lower() == ".splat" else path
        raise ValueError(f"{where}: its gdbench tags are unreadable ({e}); delete or fix it") from e


def read_tags(path: str | Path) -> FileTags:
    """The tags of the scene file at ``path`` (see the module docstring). A gdbench run's
    ``scene.ply`` from before the up comment existed records its run alone and is +Z up."""
    from gdbench.core.ply import header_comments

    path = Path(path)
    up = run = None
    source = ""
    if path.suffix.lower() == ".ply":
        for c in header_comments(path):
            key, _, value = c.partition(" ")[2].partition(" ") if c.startswith("gdbench ") else ("", "", "")
            if key == "run" and value:
                run = value.strip()
            elif key == "up":
                if value.strip() not in UP_AXES:
                    raise ValueError(
                        f"{path}: its header records up axis {value.strip()!r}; expected one of {', '.join(UP_AXES)}"
                    )
                up, source = value.strip(), "header"
        if up is None and run is not None and path.name == "scene.ply":
            up, source = "+z", "header"  # a run's own scene: always +Z up
    elif path.suffix.lower() in (".splat", ".glb", ".obj"):
        tags, where = _other_tags(path)
        if "up" in tags and tags["up"] not in UP_AXES:
            at = sidecar(path) if where == "sidecar" else path
            raise ValueError(
                f"{at}: its gdbench tags name up axis {tags['up']!r}; expected one of {', '.join(UP_AXES)} "
                "(fix or delete it)"
            )
        if "up" in tags:
            up, source = tags["up"], where
        run = tags.get("run") or None
    if up is None and (named := _name_axis(path)) is not None:
        up, source = named, "name"
    return FileTags(up, run, source)


def resolve_up(path: str | Path, asked: str | None, flag: str = "--up") -> str:
    """The up axis to read ``path`` with: ``asked`` (the command's ``flag``) or, when None, the
    file's own (``read_tags``), else +z. ``asked`` and a recorded axis that differ are refused:
    reading the file with the wrong axis would turn the scene (a -Y-up file read as +Z up lies on
    its side), and converting it again would rotate it twice."""
    tags = read_tags(path)
    if asked is None:
        return tags.up or "+z"
    label = f"{flag.lstrip('-').replace('-', '_')} ({flag})" if flag.startswith("--") else flag
    check_up(asked, label)
    if tags.up is not None and asked != tags.up:
        where = {"header": "its header", "sidecar": f"its sidecar {sidecar(path).name}", "name": "its name"}
        raise ValueError(
            f"{label}: {path} records up axis {tags.up} ({where[tags.source]}); reading it as {asked} would "
            f"turn the scene by the wrong rotation. Leave {flag} out (the file's axis is used) or pass {flag} {tags.up}"
        )
    return asked
