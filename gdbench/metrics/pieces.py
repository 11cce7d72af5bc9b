"""The connected pieces of a result's silhouettes, for the view metrics (``views``): the largest
piece of each view and the share of opacity outside it (floaters). Pure numpy, equal bit for bit
to scipy.ndimage's 4-connected labelling, without importing scipy (its import is a slow part of
every scoring process). Split from views.py (behaviour unchanged)."""

from __future__ import annotations

from torch import Tensor


def detached(alpha: Tensor, dilate: int) -> float:
    """The share of opacity outside the largest connected piece of each view's silhouette. Equal,
    bit for bit, to scipy.ndimage's label (4-connected), sum by label (per-label float64 sums in
    raster order), the first largest piece and binary_dilation by the cross (nothing outside the
    image), without importing scipy: scipy.ndimage's import is a slow part of every scoring
    process, and nothing else there needs scipy."""
    total = float(alpha.sum())
    if total <= 0:
        return 0.0
    A = alpha.double().numpy()
    body, pieces = main_piece(A)
    H, W = A.shape[1:]
    views = [f for f in range(len(A)) if pieces[f] > 1]
    if not views:
        return 0.0
    body = body[views]
    for _ in range(min(dilate, H + W)):  # within L1 distance ``dilate``; H + W steps cover the image
        grown = body.copy()
        grown[:, 1:] |= body[:, :-1]
        grown[:, :-1] |= body[:, 1:]
        grown[:, :, 1:] |= body[:, :, :-1]
        grown[:, :, :-1] |= body[:, :, 1:]
        body = grown
    out = 0.0
    for a, b in zip(A[views], body):
        out += float(a[~b].sum())
    return out / total


def main_piece(A):
    """(body, pieces) of coverage ``A`` [F, H, W] (numpy float64): each view's largest 4-connected
    piece of its silhouette (alpha over 0.1; the first of equal ones, by summed opacity) as a bool
    [F, H, W], and each view's number of pieces."""
    import numpy as np

    F, H, W = A.shape
    pixels, label, first = components(A > 0.1)
    sizes = np.bincount(label, weights=A.reshape(-1)[pixels], minlength=len(first))  # as ndimage.sum sums
    bounds = np.searchsorted(first // (H * W), np.arange(F + 1))  # each view's pieces
    chosen = np.zeros(len(first), bool)
    for f in range(F):
        if bounds[f + 1] > bounds[f]:
            chosen[bounds[f] + int(np.argmax(sizes[bounds[f] : bounds[f + 1]]))] = True
    body = np.zeros(F * H * W, bool)
    body[pixels[chosen[label]]] = True
    return body.reshape(F, H, W), np.diff(bounds)


def components(mask):
    """(pixels, label, first) of a boolean [..., H, W] ``mask``: the flat indices of its set pixels
    in raster order, the 4-connected piece of each (connected within its [H, W] plane) and each
    piece's first pixel. Pieces are numbered 0, 1, ... in the raster order of their first pixels,
    as scipy.ndimage.label numbers them from 1. Union-find over the horizontal runs: each round
    hooks the larger root of every pair of touching runs (a run and one in the next row) to the
    smaller and flattens the trees by pointer jumping, so a long snake or spiral costs a few rounds
    (2 up to 1024 px; 6 for 1024 px noise), not its length; the work per round grows with the runs
    (faster than scipy on the metric's silhouettes, slower on large noise images)."""
    import numpy as np

    W = mask.shape[-1]
    start = mask.copy()  # the first pixel of each horizontal run
    start[..., 1:] &= ~mask[..., :-1]
    pixels, starts = np.flatnonzero(mask), np.flatnonzero(start)
    below = np.zeros_like(mask)
    below[..., :-1, :] = mask[..., :-1, :] & mask[..., 1:, :]
    overlap = below.copy()  # the first column of each overlap of a run with one in the next row
    overlap[..., 1:] &= ~below[..., :-1]
    top = np.flatnonzero(overlap)
    u, w = np.searchsorted(starts, top, "right") - 1, np.searchsorted(starts, top + W, "right") - 1
    parent = np.arange(len(starts))
    while not np.array_equal(pu := parent[u], pw := parent[w]):
        lo = np.minimum(pu, pw)
        np.minimum.at(parent, pu, lo)
        np.minimum.at(parent, pw, lo)
        deep = np.flatnonzero(parent[parent] != parent)  # jump until every run's parent is a root
        while len(deep):
            parent[deep] = parent[parent[deep]]
            deep = deep[parent[deep] != parent[parent[deep]]]
    root = parent == np.arange(len(parent))
    run = np.cumsum(start.reshape(-1)[pixels]) - 1  # the run of each set pixel
    return pixels, (np.cumsum(root) - 1)[parent][run], starts[root]
