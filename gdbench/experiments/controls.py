"""The mechanism's controls, measured at the denoiser (docs/decisive.md, "The controls").

    python -m gdbench.experiments.controls --out docs/results/controls [--draws 8]

Which property of structured noise acts? Each arm removes one: gd-no-sn all of it,
gd-redraw-step the persistence across steps (at --views-per-step 4 its views of one step still
share noise in 3D), gd-pose-locked the 3D correspondence between views (a fixed 2D field per
pose: persistent, the same statistics). This measures, for each arm, the noise fields the
trainer hands the denoiser (``train.distill._noise_fields``, the trainer's own code, at the
learned prior's input resolution of the decisive setting, with the mixing ratio held at r: 0.3
is the schedule's start, 1 the structured part alone):

- ``variance``, ``mean``: the marginal per pixel and channel (1 and 0 by design);
- ``corr_length_px``: the spatial correlation length (``noise.autocorrelation_length`` over
  independent draws at one camera: the spectrum's width);
- ``persist_lag1``, ``persist_lag100``: correlation at the same pose and pixel between step t
  and t+1 (t+100);
- ``surface_<d>``: correlation at the same *surface point* of view A (step t) and view B, d
  degrees of azimuth away (view B's field warped into A by the asset's depth, as
  ``priors.learned.evaluation.warped_corr``), B at step t+1 (``next``) or in the same step
  (``same``, only where the arm renders several views per step);
- ``pixel_<d>``: the same pair's correlation at the same *pixel* (image-locked sharing).

Each value is the mean over ``draws`` seeds x captions; controls.csv holds every row with the
commit, controls.md the table docs/decisive.md quotes.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

import torch

ARMS: list[tuple[str, str, dict]] = [
    ("gd", "gd", {}),
    ("gd-redraw-step", "gd-redraw-step", {}),
    ("gd-redraw-step, 4 views", "gd-redraw-step", {"views.per_step": 4, "views.spread_deg": 10.0}),
    ("gd-pose-locked", "gd-pose-locked", {}),
    ("gd-no-sn", "gd-no-sn", {}),
]
"""(label, preset, overrides) of each arm."""
SEPARATIONS = (0.0, 5.0, 30.0, 90.0)
CAPTIONS = ("a yellow duck", "a corgi", "a penguin")
ELEVATION, FOVY = 15.0, 55.0


def _views(ctx, az: list[float]):
    from gdbench.core.camera import SphericalPoses
    from gdbench.train.views import Views

    n = len(az)
    f64 = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    poses = SphericalPoses(f64(az), f64([ELEVATION] * n), f64([ctx.cfg.camera_radius] * n), f64([FOVY] * n))
    size = ctx.cfg.resolution // ctx.factor
    cams = poses.cameras(size, size)
    return Views(poses, cams, cams, 1.0, 1.0)


def _fields(ctx, state, az: list[float], step: int) -> torch.Tensor:
    """The noise the denoiser gets at ``step`` for views at azimuths ``az`` [V, h, w, C]."""
    from gdbench.train.distill import _noise_fields

    state.step = step
    views = _views(ctx, az)
    size = views.prior_cams.height
    shape = (len(az), size, size, ctx.prior.channels)
    return _noise_fields(ctx, state, views, shape, True)[0]


@functools.lru_cache(maxsize=512)
def _depth_pair(caption: str, a0: float, sep: float, size: int):
    """(z, cams) of the asset at azimuths a0 and a0 + sep: the same for every arm (one render)."""
    from gdbench.priors.learned.evaluation import render_views

    _, z, cams = render_views(caption, torch.tensor([a0, a0 + sep]), ELEVATION, FOVY, size=size, depth=True)
    return z, cams


def measure_arm(prior, preset_name: str, overrides: dict, ratio: float, *, draws: int, seed0: int = 0) -> dict:
    """The statistics of one arm at mixing ratio ``ratio`` (see the module docstring)."""
    from gdbench.mechanisms.noise import autocorrelation_length
    from gdbench.priors.learned.evaluation import pearson, warped_corr
    from gdbench.train.config import preset
    from gdbench.train.trainer import init_state, make_context

    vals: dict[str, list[float]] = {}
    add = lambda k, v: vals.setdefault(k, []).append(v)  # noqa: E731
    at_one_camera = []
    g = torch.Generator().manual_seed(seed0)
    for d in range(draws):
        cfg = preset(preset_name, prior="learned", seed=seed0 + d, steps=1000, progress=False, **overrides,
                     **{"noise.ratio_start": ratio, "noise.ratio_end": ratio})  # fmt: skip
        ctx = make_context(cfg, prior)
        state = init_state(ctx)
        several = cfg.views.per_step > 1
        a0 = float(torch.rand(1, generator=g) * 360 - 180)
        n0 = _fields(ctx, state, [a0], 1)
        at_one_camera.append(_fields(ctx, state, [0.0], 2)[0])
        add("mean", float(n0.mean()))
        add("variance", float(n0.double().var()))
        add("persist_lag1", pearson(n0, _fields(ctx, state, [a0], 3)))
        for t in range(4, 103):
            _fields(ctx, state, [a0 + 180.0], t)  # steps between, looking elsewhere
        add("persist_lag100", pearson(n0, _fields(ctx, state, [a0], 103)))
        step = 104
        for caption in CAPTIONS:
            for sep in SEPARATIONS[1:]:
                z, cams = _depth_pair(caption, a0, sep, ctx.cfg.resolution // ctx.factor)
                pair = [_fields(ctx, state, [a0], step), _fields(ctx, state, [a0 + sep], step + 1)]
                modes = {"next": torch.cat(pair)}
                if several:
                    modes["same"] = _fields(ctx, state, [a0, a0 + sep], step + 2)
                step += 3
                for mode, n in modes.items():
                    add(f"surface_{sep:g}_{mode}", warped_corr(n, z, cams))
                    add(f"pixel_{sep:g}_{mode}", pearson(n[0], n[1]))
    field = torch.cat(at_one_camera, -1)  # [h, w, draws x C]: independent draws at one camera
    cover = torch.ones(field.shape[:2] + (1,))
    row = {k: sum(v) / len(v) for k, v in vals.items()}
    return row | {"corr_length_px": autocorrelation_length(field, cover)}


def measure(*, draws: int = 8, ratios=(0.3, 1.0)) -> list[dict]:
    from gdbench.priors.factory import make_prior
    from gdbench.train.config import preset

    prior = make_prior(preset("gd", prior="learned"))
    rows = []
    for label, name, overrides in ARMS:
        for r in ratios:
            print(f"controls: {label}, ratio {r}", flush=True)
            rows.append({"arm": label, "preset": name, "overrides": overrides or "", "ratio": r,
                         **measure_arm(prior, name, overrides, r, draws=draws)})  # fmt: skip
    return rows


COLUMNS = [("variance", "variance"), ("corr_length_px", "corr. length (px)"), ("persist_lag1", "same pose, t+1"),
           ("persist_lag100", "same pose, t+100")] + [
    (f"{kind}_{s:g}_{mode}", f"{kind} {s:g}° ({mode})")
    for mode in ("next", "same") for kind in ("surface", "pixel") for s in SEPARATIONS[1:]
]  # fmt: skip


def markdown(rows: list[dict], commit: str) -> str:
    """The table of ``rows`` (one per arm and ratio) for docs/decisive.md."""
    lines = [f"Noise at the denoiser's input (commit {commit}); 'next': view B one step after view A; "
             "'same': both in one step (only arms with several views per step); '-': the arm never has it.", "",
             "| arm | r | " + " | ".join(h for _, h in COLUMNS) + " |",
             "|" + "---|" * (len(COLUMNS) + 2)]  # fmt: skip
    for r in rows:
        cells = [f"{r[k]:.2f}" if isinstance(r.get(k), float) else "-" for k, _ in COLUMNS]
        lines.append(f"| {r['arm']} | {r['ratio']:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit

    p = argparse.ArgumentParser(prog="python -m gdbench.experiments.controls", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for controls.csv and controls.md")
    p.add_argument("--draws", type=int, default=8, help="seeds per arm (each with 3 captions; default 8)")
    a = p.parse_args(argv)
    if a.draws < 1:
        p.error(f"--draws: expected at least 1, got {a.draws}")
    commit = code_commit()
    rows = [r | {"commit": commit} for r in measure(draws=a.draws)]
    a.out.mkdir(parents=True, exist_ok=True)
    write_csv(rows, a.out / "controls.csv")
    (a.out / "controls.md").write_text(markdown(rows, commit))
    print(f"controls: wrote {a.out / 'controls.csv'} and {a.out / 'controls.md'}")


if __name__ == "__main__":
    main()
