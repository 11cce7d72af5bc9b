"""Figures of a sweep's cells: their turntables side by side (``turntable_grid``), what a reader
looks at beside the tables."""

from __future__ import annotations

from pathlib import Path

from gdbench.experiments.sweep import SETTINGS, cell_name


def turntable_grid(
    out: Path | list[Path], prompt: str | None, seed: int = 0, frames: int = 6, setting: str | None = None,
    group: str | None = None, path: Path | None = None,
) -> Path | None:  # fmt: skip
    """One figure of turntables (``frames`` evenly spaced views from each cell's turntable.gif), a
    row per cell of ``seed``: for ``prompt``, one per (group, setting, preset); with ``prompt``
    None, one per (group, prompt, preset) of ``setting``; ``group`` keeps one group's cells.
    ``out`` may be several sweep folders (their cells in one figure, by setting, group, prompt and
    preset), saved at ``path`` (default: the first folder). None when no cell has one."""
    import imageio.v3 as iio
    import numpy as np

    from gdbench.core.plotting import pyplot, save
    from gdbench.train.config import PRESETS

    roots = [Path(o) for o in (out if isinstance(out, (list, tuple)) else [out])]

    def parts(root: Path, gif: Path) -> tuple[str, str, str, str]:
        """(group, setting, prompt folder, preset) of a cell's gif under root/cells."""
        rel = gif.relative_to(root / "cells").parts  # [group/]setting/prompt/preset/seedK/turntable.gif
        return ("" if len(rel) == 5 else rel[0], *rel[-5:-2])

    def keep(root: Path, gif: Path) -> bool:
        g, st, pr, _ = parts(root, gif)
        return ((group is None or g == group) and (prompt is None or pr == cell_name(prompt))
                and (prompt is not None or setting is None or st == setting))  # fmt: skip

    def order(cell: tuple[Path, Path]) -> tuple:
        g, st, pr, preset_ = parts(*cell)
        st_i = list(SETTINGS).index(st) if st in SETTINGS else 99
        key = (g, pr if prompt is None else "", st_i, list(PRESETS).index(preset_) if preset_ in PRESETS else 99)
        return (st_i, *key) if len(roots) > 1 else key  # several sweeps: by setting first

    found = ((root, g) for root in roots for g in (root / "cells").rglob(f"seed{seed}/turntable.gif"))
    cells = sorted((c for c in found if keep(*c)), key=order)
    if not cells:
        return None
    plt = pyplot()
    height = 1.7 * len(cells) + 0.5  # inches: the title's half inch above the first row
    fig, axes = plt.subplots(len(cells), 1, figsize=(1.6 * frames, height), squeeze=False)
    fig.subplots_adjust(top=1 - 0.6 / height, bottom=0.1 / height)
    for ax, (root, gif) in zip(axes[:, 0], cells):
        video = iio.imread(gif)
        pick = np.linspace(0, len(video), frames, endpoint=False).astype(int)
        ax.imshow(np.concatenate([video[i][..., :3] for i in pick], 1))
        g, setting_, folder, preset = parts(root, gif)
        text = f"{setting_}: {preset}" if prompt is not None else f"{folder.replace('_', ' ')}: {preset}"
        ax.set_title(f"{g} / {text}" if g else text, loc="left", fontsize=8, pad=2)
        ax.set_xticks([])
        ax.set_yticks([])
    tail = "" if group is None else f"_{group or 'ungrouped'}"
    if prompt is not None:
        fig.suptitle(f"'{prompt}', seed {seed}: turntables per setting and preset", fontsize=9, y=1 - 0.1 / height)
        return save(fig, path or roots[0] / f"turntables_{cell_name(prompt)}{tail}.png", dpi=90)
    fig.suptitle(
        f"{setting or 'all settings'}, seed {seed}: turntables per prompt and preset", fontsize=9, y=1 - 0.1 / height
    )
    return save(fig, path or roots[0] / f"turntables_{setting or 'all'}{tail}.png", dpi=90)
