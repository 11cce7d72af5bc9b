"""The learned prior checked against oracles (scripts/eval_learned_prior.py writes the tables and
figures of docs/learned_prior.md from these).

- ``denoising_error``: the model's x0 estimate against the exact posterior mean of its own training
  distribution (the empirical distribution of its training views, weighted by its front bias),
  which is the optimal denoiser for that distribution, per noise level.
- ``off_grid``: at cameras between the image bank's (azimuth, elevation, fov off its grid), the
  learned prior's estimate against the runtime empirical prior's, both against the true render.
- ``sample_scores``: DDIM samples per caption and view, matched to ground-truth renders of every
  caption, variant and azimuth.
- ``mechanism``: whether structured noise makes a prior's predictions of two views 30 degrees apart
  more alike (after warping one into the other with the asset's depth) than independent noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F

SIZE = 32


def exact_posterior_mean(y: Tensor, sigma: Tensor, images: Tensor, log_weights: Tensor | None = None) -> Tensor:
    """E[x0 | y] [B, ...] for y = x0 + sigma n, x0 drawn from ``images`` [N, ...] with prior
    log-weights ``log_weights`` [N] (None: uniform); squared distances in float64."""
    B = y.shape[0]
    yf, X = y.reshape(B, -1).double(), images.reshape(images.shape[0], -1).double()
    d2 = torch.cdist(yf, X, compute_mode="donot_use_mm_for_euclid_dist") ** 2
    logits = -d2 / (2 * sigma.double().reshape(B, 1) ** 2)
    if log_weights is not None:
        logits = logits + log_weights.double()[None]
    w = torch.softmax(logits, 1)
    return (w @ X).to(y.dtype).reshape(y.shape)


def render_views(caption: str, azimuth, elevation, fovy, *, variant: int = 0, size: int = SIZE, depth: bool = False):
    """Ground-truth renders [V, size, size, 3] in [-1, 1] of an asset at the given cameras (64 px
    renders box-filtered to ``size``, as the model's data), and camera z [V, size, size] if asked
    (rendered at ``size``) and the cameras at ``size``."""
    from gdbench.assets.library import build
    from gdbench.core.camera import SphericalPoses
    from gdbench.priors.learned.data import to_model_images
    from renderers.pyrender_points.mesh import render_mesh

    f64 = lambda v: torch.as_tensor(v, dtype=torch.float64).reshape(-1)  # noqa: E731
    az, el, fv = f64(azimuth), f64(elevation), f64(fovy)
    n = max(len(az), len(el), len(fv))
    poses = SphericalPoses(az.expand(n), el.expand(n), torch.ones(n, dtype=torch.float64), fv.expand(n))
    mesh = build(caption, variant)
    pose_gl, K = poses.cameras(64, 64).to_opengl()
    rgb, _, _ = render_mesh(mesh, pose_gl.double().numpy(), K.double().numpy(), 64, 64)
    img = to_model_images(torch.from_numpy(rgb), size).permute(0, 2, 3, 1)
    if not depth:
        return img
    pose_gl, K = poses.cameras(size, size).to_opengl()
    _, z, _ = render_mesh(mesh, pose_gl.double().numpy(), K.double().numpy(), size, size, supersample=1)
    return img, torch.from_numpy(z), poses.cameras(size, size)


# ----------------------------------------------------------------------------- denoising error
def denoising_error(prior, data, sigmas: list[float], *, queries: int = 48, seed: int = 0) -> list[dict]:
    """Per caption (variant 0) and noise level: MSE of the learned prior's x0 estimate (camera
    dropped, no guidance: the model's own posterior mean) to the exact posterior mean over its
    training views of that caption and variant, weighted as its training drew them; with the exact
    posterior's own error to the clean view (the irreducible part) for scale. Queries are training
    views drawn with the same weights."""
    from gdbench.priors.learned.data import to_model_images, view_weights

    if prior.guidance_scale != 1 or prior.view_mode != "none":
        raise ValueError("prior: the oracle compares the model's own posterior mean (guidance 1, view_mode 'none')")
    kappa = prior.front_bias
    g = torch.Generator().manual_seed(seed)
    rows = []
    for c, caption in enumerate(data.captions):
        sel = torch.nonzero((data.caption == c) & (data.variant == 0))[:, 0]
        X = to_model_images(data.images[sel], prior.size).permute(0, 2, 3, 1)
        w = view_weights(data.azimuth[sel], kappa)
        cond = prior.encode(caption)
        for s in sigmas:
            idx = torch.multinomial(w.float(), queries, replacement=True, generator=g)
            x0 = X[idx]
            y = x0 + s * torch.randn(x0.shape, generator=g)
            sig = torch.full((queries,), s)
            exact = exact_posterior_mean(y, sig, X, torch.log(w))
            learned = prior.denoise(y, sig, cond)
            mse = lambda a, b: float(((a - b) ** 2).mean())  # noqa: E731
            rows.append({"caption": caption, "sigma": s, "mse_learned_exact": mse(learned, exact),
                         "mse_exact_x0": mse(exact, x0), "mse_learned_x0": mse(learned, x0)})  # fmt: skip
    return rows


# ----------------------------------------------------------------------------- off the bank's grid
def sharpness(img: Tensor) -> Tensor:
    """Mean absolute Laplacian per image [B] of images [B, H, W, 3] (high-frequency content)."""
    x = img.permute(0, 3, 1, 2)
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]]).expand(3, 1, 3, 3)
    return torch.nn.functional.conv2d(x, k, groups=3).abs().mean((1, 2, 3))


def psnr(a: Tensor, b: Tensor) -> Tensor:
    """PSNR [B] (dB) of images in [-1, 1] (peak 2): the GT scores' PSNR on [0, 1]."""
    from gdbench.metrics.gt import psnr as psnr01

    return psnr01((a + 1) / 2, (b + 1) / 2)


def off_grid(learned, empirical, captions: list[str], sigmas: list[float], *, seed: int = 0):
    """At cameras between the bank's (azimuth 2.5 deg off its 5-deg grid, elevation 10 deg off its
    20-deg rings, fovy off its 0.5-deg zoom levels): PSNR to the true render and sharpness (relative
    to the true render's) of each prior's estimate. Returns (rows, example images)."""
    g = torch.Generator().manual_seed(seed)
    az = torch.tensor([2.5, 47.5, 92.5, 137.5, 182.5, 227.5, 272.5, 317.5])
    el = torch.tensor([10.0, -30.0, 30.0, -10.0, 10.0, 30.0, -10.0, -30.0])
    fv = torch.tensor([47.25, 52.75, 61.25, 43.75, 66.25, 57.75, 49.25, 55.25])
    rows, examples = [], {}
    for caption in captions:
        x0 = render_views(caption, az, el, fv)
        for s in sigmas:
            y = x0 + s * torch.randn(x0.shape, generator=g)
            sig = torch.full((len(az),), s)
            kw = dict(azimuth=az, elevation=el, fovy=fv)
            out = {
                "learned": learned.denoise(y, sig, learned.encode(caption), **kw),
                "empirical": empirical.denoise(y, sig, empirical.encode(caption), **kw),
            }
            for name, D in out.items():
                rows.append({"caption": caption, "sigma": s, "prior": name, "psnr": float(psnr(D, x0).mean()),
                             "sharpness": float((sharpness(D) / sharpness(x0)).mean())})  # fmt: skip
            examples[(caption, s)] = (x0[0], y[0], out["empirical"][0], out["learned"][0])
    return rows, examples


# ----------------------------------------------------------------------------- samples
@dataclass(frozen=True)
class Match:
    caption: int
    variant: int
    azimuth: float


def reference_set(captions: list[str], *, elevation: float = 15.0, fovy: float = 55.0, azimuths: int = 36):
    """Renders [C, Vr, A, size, size, 3] of every caption, variant and azimuth (ground truth)."""
    from gdbench.assets.library import VARIANTS

    az = torch.arange(azimuths) * (360.0 / azimuths) - 180.0
    refs = torch.stack(
        [torch.stack([render_views(c, az, elevation, fovy, variant=v) for v in range(VARIANTS)]) for c in captions]
    )
    return refs, az


def to_size(images: Tensor, size: int) -> Tensor:
    """Images [B, h, h, 3] box-filtered to [B, size, size, 3] (h a multiple of ``size``): a 64 px
    model's samples are matched to the same 32 px references as a 32 px model's."""
    h = images.shape[1]
    if h == size:
        return images
    if h % size:
        raise ValueError(f"images: expected a multiple of {size} px, got {h}")
    return F.avg_pool2d(images.permute(0, 3, 1, 2), h // size).permute(0, 2, 3, 1)


def match(images: Tensor, refs: Tensor, ref_az: Tensor) -> list[Match]:
    """Nearest reference (MSE) of each image [B, size, size, 3]."""
    C, V, A = refs.shape[:3]
    d = torch.cdist(images.reshape(len(images), -1).double(), refs.reshape(C * V * A, -1).double())
    best = d.argmin(1).tolist()
    return [Match(i // (V * A), (i // A) % V, float(ref_az[i % A])) for i in best]


def _circ(d: float) -> float:
    return abs((d + 180.0) % 360.0 - 180.0)


def sample_scores(prior, refs: Tensor, ref_az: Tensor, *, views=(0.0, 90.0, 180.0, -90.0), seeds: int = 8,
                  camera: bool = True, elevation: float = 15.0, fovy: float = 55.0, steps: int = 30):  # fmt: skip
    """DDIM samples of every caption (variant 0) at each asked azimuth, with the camera given or
    dropped; returns (rows: one per sample with its match, images [C, len(views), seeds, ...])."""
    rows, grid = [], []
    for c, caption in enumerate(prior.captions):
        cond = prior.encode(caption)
        cam = torch.tensor([[a, elevation, fovy] for a in views for _ in range(seeds)])
        g = torch.Generator().manual_seed(1000 + c)
        x = prior.sample(cond, cam if camera else None, generator=g, steps=steps, n=len(cam))
        grid.append(x.reshape(len(views), seeds, *x.shape[1:]))
        for i, m in enumerate(match(to_size(x, refs.shape[-2]), refs, ref_az)):
            asked = float(cam[i, 0])
            rows.append({
                "caption": caption, "asked_azimuth": asked, "camera": camera,
                "matched_caption": prior.captions[m.caption], "matched_variant": m.variant,
                "matched_azimuth": m.azimuth, "caption_ok": m.caption == c, "variant_ok": m.variant == 0,
                "azimuth_ok": _circ(m.azimuth - asked) <= 45.0,
                "front": _circ(m.azimuth) < 45.0, "back": _circ(m.azimuth) > 135.0,
            })  # fmt: skip
    return rows, torch.stack(grid)


# ----------------------------------------------------------------------------- the mechanism
def warp(src: Tensor, depth_dst: Tensor, cams_dst, cams_src, depth_src: Tensor, tol: float = 0.03):
    """``src`` [h, w, 3] (seen by camera ``cams_src``) resampled into the destination camera's pixels
    using the destination's depth; returns (warped [h, w, 3], valid [h, w]): pixels on the object in
    both views, not occluded in the source (depths agree within ``tol`` relative)."""
    h, w = depth_dst.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")  # fmt: skip
    K, c2w = cams_dst.Ks[0].double(), cams_dst.camtoworlds[0].double()
    z = depth_dst.double()
    pc = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    pw = pc.reshape(-1, 3) @ c2w[:3, :3].T + c2w[:3, 3]
    uv, zs = cams_src.project(pw.float())
    uv, zs = uv[0].double(), zs[0].double()
    gx, gy = uv[:, 0] / w * 2 - 1, uv[:, 1] / h * 2 - 1
    grid = torch.stack([gx, gy], -1).reshape(1, h, w, 2).float()
    sampled = torch.nn.functional.grid_sample(src.permute(2, 0, 1)[None].float(), grid, align_corners=False)[0]
    zsrc = torch.nn.functional.grid_sample(depth_src[None, None].float(), grid, mode="nearest", align_corners=False)
    zsrc = zsrc[0, 0].double().reshape(-1)
    # inside the source image by half a pixel: bilinear samples nearer the border mix in zero padding
    inside = (uv[:, 0] >= 0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= 0.5) & (uv[:, 1] <= h - 0.5)
    valid = (z.reshape(-1) > 0) & inside & (zsrc > 0) & ((zsrc - zs).abs() < tol * zs)
    return sampled.permute(1, 2, 0), valid.reshape(h, w)


def mechanism(prior, captions: list[str], *, sigmas=(2.0, 6.0), draws: int = 16, ratios=(1.0, 0.3),
              separation: float = 30.0, seed: int = 0) -> list[dict]:  # fmt: skip
    """For each caption, two cameras ``separation`` degrees apart (elevation 15, fovy 55): render
    the asset, add noise at sigma with (a) independent fields in the two views and (b) structured
    noise from one cloud (mixed with iid noise as the trainer mixes it, ``noise.mix`` with the
    default ratio mode: 1 = pure structured noise; the trainer's schedule starts at 0.3), denoise
    both views, warp view B's prediction into view A with the asset's depth and take
    the MSE to A's prediction over the pixels both views see, and the correlation of the two
    predictions' departures from the truth (view B's warped likewise): whether what the noise made
    in one view is made in the other. One row per (caption, sigma, ratio, draw) with both noises'
    values (the same draw of everything else: a paired comparison)."""
    from gdbench.mechanisms.noise import NoiseConfig, mix

    g = torch.Generator().manual_seed(seed)
    rows = []
    for caption in captions:
        a0 = float(torch.rand(1, generator=g) * 360 - 180)
        az = torch.tensor([a0, a0 + separation])
        x0, z, cams = render_views(caption, az, 15.0, 55.0, depth=True)
        clean_b = warp(x0[1], z[0], cams[0], cams[1], z[1])[0]  # view B's truth seen from A
        cond = prior.encode(caption)
        for s in sigmas:
            for ratio in ratios:
                for d in range(draws):
                    n_s = source_noise(noise_source(g), cams, g)
                    iid = torch.randn((2, *x0.shape[1:]), generator=g)
                    n_b = mix(n_s, ratio, generator=g, mode=NoiseConfig().ratio)
                    out = {"noise_corr": warped_corr(n_b, z, cams)}
                    for name, n in (("independent", iid), ("structured", n_b)):
                        y = x0 + s * n
                        D = prior.denoise(y, torch.full((2,), s), cond, azimuth=az, elevation=torch.full((2,), 15.0),
                                          fovy=torch.full((2,), 55.0))  # fmt: skip
                        wb, valid = warp(D[1], z[0], cams[0], cams[1], z[1])
                        out[name] = float(((D[0] - wb) ** 2)[valid].mean())
                        # how alike the two views' departures from the truth are (what the noise made)
                        out[f"{name}_corr"] = pearson((D[0] - x0[0])[valid], (wb - clean_b)[valid])
                        out["pixels"] = int(valid.sum())
                    rows.append({"caption": caption, "separation": separation, "sigma": s, "ratio": ratio, "draw": d,
                                 **out})  # fmt: skip
    return rows


def surface_coupling(captions: list[str], separations, *, ratios=(1.0, 0.3), draws: int = 8, size: int = 64,
                     seed: int = 0) -> list[dict]:  # fmt: skip
    """How much structured noise two training views share at the same surface point: for each
    caption and azimuth separation (elevation 15, fovy 55, a random first azimuth), the correlation
    of the two views' noise fields at the asset's surface points both see (view B's warped into A
    by depth), for the default noise cloud mixed as the trainer mixes it at each ratio (1: pure
    structured noise; the schedule starts at 0.3). iid noise would read 0."""
    from gdbench.mechanisms.noise import NoiseConfig, mix

    g = torch.Generator().manual_seed(seed)
    rows = []
    for caption in captions:
        a0 = float(torch.rand(1, generator=g) * 360 - 180)
        for sep in separations:
            _, z, cams = render_views(caption, torch.tensor([a0, a0 + sep]), 15.0, 55.0, size=size, depth=True)
            for d in range(draws):
                n_s = source_noise(noise_source(g), cams, g)
                for r in ratios:
                    n = mix(n_s, r, generator=g, mode=NoiseConfig().ratio)
                    rows.append({"caption": caption, "separation": float(sep), "ratio": r, "draw": d,
                                 "noise_corr": warped_corr(n, z, cams)})  # fmt: skip
    return rows


def noise_source(generator: torch.Generator):
    """(cloud, colours): one draw of the trainer's default noise cloud and its RGB colours."""
    from gdbench.mechanisms.noise import NoiseConfig, init_colors, make_noise_cloud

    cloud = make_noise_cloud(NoiseConfig(), 3, generator=generator)
    return cloud, init_colors(cloud, generator=generator).colors


def source_noise(source, cams, generator: torch.Generator) -> Tensor:
    """The structured noise n_s [V, h, w, 3] of a ``noise_source`` seen by ``cams``."""
    from gdbench.mechanisms.noise import NoiseRenderer

    cloud, colors = source
    return NoiseRenderer(cloud, cache_size=0).render(colors, cams, generator=generator).noise


def warped_corr(n: Tensor, z: Tensor, cams) -> float:
    """Correlation of view A's field with view B's warped into A over the pixels both see: how much
    of the noise reaches both views at the same surface point (iid noise: 0)."""
    wb, valid = warp(n[1], z[0], cams[0], cams[1], z[1])
    return pearson(n[0][valid], wb[valid])


def pearson(a: Tensor, b: Tensor) -> float:
    """Pearson correlation of two equally shaped sets of values."""
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-12))


def paired_ratio(rows: list[dict], *, seed: int = 0, boot: int = 2000) -> dict:
    """Mean of structured / independent MSE over the rows, and the mean paired difference of the
    departures' correlation (structured - independent), each with a 95% bootstrap interval."""
    rng = np.random.default_rng(seed)

    def interval(v: np.ndarray) -> tuple[float, float, float]:
        means = v[rng.integers(0, len(v), (boot, len(v)))].mean(1)
        lo, hi = np.quantile(means, [0.025, 0.975])
        return float(v.mean()), float(lo), float(hi)

    r = interval(np.array([x["structured"] / x["independent"] for x in rows]))
    c = interval(np.array([x["structured_corr"] - x["independent_corr"] for x in rows]))
    mean = lambda k: float(np.mean([x[k] for x in rows]))  # noqa: E731
    return {"ratio": r[0], "lo": r[1], "hi": r[2], "corr_independent": mean("independent_corr"),
            "corr_structured": mean("structured_corr"), "corr_diff": c[0], "corr_lo": c[1], "corr_hi": c[2],
            "n": len(rows)}  # fmt: skip


# ----------------------------------------------------------------------------- the camera
SIX_AZIMUTHS = (0.0, 60.0, 120.0, 180.0, -120.0, -60.0)
"""The checks' cameras: six azimuths about the asset, at elevation 15 and fovy 55."""


def noised_renders(prior, captions: list[str], sigmas, seed: int = 0):
    """(caption, its condition, sigma, renders [6, size, size, 3] at ``SIX_AZIMUTHS`` (the prior's
    size), those renders noised at sigma) for each caption and sigma in turn, the noise drawn from
    one generator of ``seed`` in that order."""
    g = torch.Generator().manual_seed(seed)
    for caption in captions:
        x0 = render_views(caption, torch.tensor(SIX_AZIMUTHS), 15.0, 55.0, size=prior.size)
        cond = prior.encode(caption)
        for s in sigmas:
            yield caption, cond, s, x0, x0 + s * torch.randn(x0.shape, generator=g)


def camera_sensitivity(prior, captions: list[str], *, sigmas=(2.0, 5.0, 10.0), offsets=(0.0, 90.0, 180.0),
                       seed: int = 0) -> list[dict]:  # fmt: skip
    """Does the prior see the camera? Renders of each caption at six azimuths (elevation 15, fovy
    55), noised at sigma and denoised with the right camera and with its azimuth turned by each
    offset: the PSNR of the estimates to the renders (a prior that ignores the azimuth reads the same
    at every offset)."""
    az, n = torch.tensor(SIX_AZIMUTHS), len(SIX_AZIMUTHS)
    rows = []
    for caption, cond, s, x0, y in noised_renders(prior, captions, sigmas, seed):
        for off in offsets:
            D = prior.denoise(y, torch.full((n,), s), cond, azimuth=az + off, elevation=torch.full((n,), 15.0),
                              fovy=torch.full((n,), 55.0))  # fmt: skip
            rows.append({"caption": caption, "sigma": s, "offset_deg": off, "psnr": float(psnr(D, x0).mean())})
    return rows


# ----------------------------------------------------------------------------- guidance in one call
def guided_error(student, teacher, unguided, captions: list[str], *, sigmas=(0.5, 2.0, 5.0, 10.0),
                 seed: int = 0) -> list[dict]:  # fmt: skip
    """A distilled model (``student``, one call) against its teacher's two-call guided prediction
    (``teacher``: the teacher at the student's scale): renders of each caption at six azimuths
    (elevation 15, fovy 55, the camera given), noised at sigma; per caption and sigma the MSE of the
    student's x0 estimate to the teacher's, beside how far guidance itself moves the teacher's
    estimate (its MSE to ``unguided``, the teacher at scale 1) and each estimate's PSNR to the
    render."""
    n = len(SIX_AZIMUTHS)
    cam = {"azimuth": torch.tensor(SIX_AZIMUTHS), "elevation": torch.full((n,), 15.0), "fovy": torch.full((n,), 55.0)}
    mse = lambda a, b: float(((a - b) ** 2).mean())  # noqa: E731
    rows = []
    for caption, cond, s, x0, y in noised_renders(teacher, captions, sigmas, seed):
        sig = torch.full((n,), s)
        d_s, d_t = student.denoise(y, sig, cond, **cam), teacher.denoise(y, sig, cond, **cam)
        d_u = unguided.denoise(y, sig, cond, **cam)
        rows.append({"caption": caption, "sigma": s, "mse_student_teacher": mse(d_s, d_t),
                     "mse_guided_unguided": mse(d_t, d_u), "psnr_student": float(psnr(d_s, x0).mean()),
                     "psnr_teacher": float(psnr(d_t, x0).mean())})  # fmt: skip
    return rows
