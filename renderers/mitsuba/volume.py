"""Exact emission-absorption rendering of the Gaussian mixture (the physics splatting approximates).

Density and emitted colour of the mixture:

    rho(x)   = sum_i rho_i G_i(x),      G_i(x) = exp(-1/2 (x - mu_i)^T Sigma_i^-1 (x - mu_i))
    c(x)     = sum_i rho_i G_i(x) c_i / rho(x)
    L(ray)   = int T(t) rho(x(t)) c(x(t)) dt + T(inf) background,    T(t) = exp(-int_0^t rho)

Opacity to density: a Gaussian seen through its centre along an axis of scale s has optical
depth rho_i s sqrt(2 pi); setting 1 - exp(-tau) = o_i gives

    rho_i = -ln(1 - o_i) / (sqrt(2 pi) s_i)

with s_i the geometric mean of the three scales (``density_from="geomean"``, the default) or
the smallest scale (``"min"``). Both are exact for isotropic Gaussians (alpha o_i from every
side). No choice can be exact for anisotropic ones: splatting's alpha does not depend on the
view, a volume's does. Measured (splat vs volume, mean |error|): the random 10k cloud 0.035
(geomean) vs 0.052 (min); the needle fixture 0.011 vs 0.034; but the crossing discs (0.01 x
0.25 x 0.25, opacity 0.7, seen face-on: geomean gives them alpha 0.13) 0.19 vs 0.12. Colours are the
degree-0 SH colour (c = C0 f_dc + 0.5); higher bands are not supported here.

Rendering: a Python Mitsuba integrator (``RBIntegrator``, path-replay backward) marches S
steps through the scene's box, jittered per sample (``spp`` per pixel), treating each step as
a homogeneous segment: alpha_k = 1 - exp(-rho_k dt), emission alpha_k c_k. The field comes
either from two Mitsuba ``gridvolume``s (rho and rho c at resolution R, trilinear; built in
torch from the Gaussians, so gradients flow grid -> Gaussians) or from the mixture evaluated
analytically in Dr.Jit (unrolled over the Gaussians: for scenes of at most ``MAX_ANALYTIC``).
Both give gradients back to torch through ``drjit.wrap``. Error falls as S, R and spp grow.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from renderers.splat import RenderOutput
from renderers.splat.composite import finish_images
from renderers.splat.project import covariance_factor

from ._lib import import_mitsuba, mitsuba_cameras, sensor_dict

MAX_ANALYTIC = 32
"""Largest scene the analytic mode accepts (its Dr.Jit kernel is unrolled over the Gaussians)."""
_SQRT_2PI = math.sqrt(2 * math.pi)


def density_scale(opacities: Tensor, scales: Tensor, density_from: str = "geomean") -> Tensor:
    """rho_i from o_i (see the module docstring); o is clamped below 1 - 1e-6."""
    if density_from not in ("geomean", "min"):
        raise ValueError(f"density_from: expected 'geomean' or 'min', got {density_from!r}")
    s = scales.clamp_min(1e-12)
    s = s.log().mean(-1).exp() if density_from == "geomean" else s.amin(-1)
    return -torch.log1p(-opacities.clamp(0, 1 - 1e-6)) / (_SQRT_2PI * s)


def scene_box(means: Tensor, scales: Tensor, pad: float = 3.5) -> tuple[Tensor, Tensor]:
    """Axis-aligned box holding every Gaussian to ``pad`` standard deviations."""
    r = pad * scales.amax(-1, keepdim=True)
    return (means - r).amin(0).detach(), (means + r).amax(0).detach()


def build_grid(means, quats, scales, opacities, colors, res: int, lo: Tensor, hi: Tensor,
               block: int | None = None, density_from: str = "geomean") -> tuple[Tensor, Tensor]:  # fmt: skip
    """rho [R, R, R] and rho c [R, R, R, 3] at voxel centres, indexed [z, y, x] (Mitsuba's layout).

    Differentiable in torch. Work is blocked: each block of ``block``^3 voxels evaluates only
    the Gaussians whose 4-sigma box overlaps it."""
    block = block or max(8, res // 8)  # at most 8^3 blocks: the loop over blocks runs in Python
    rho_i = density_scale(opacities, scales, density_from)
    M = covariance_factor(quats, scales)  # Sigma = M M^T
    prec = torch.linalg.inv(M @ M.transpose(-1, -2))
    ext = 4.0 * scales.amax(-1)
    axes = [lo[d] + (torch.arange(res, dtype=means.dtype) + 0.5) / res * (hi[d] - lo[d]) for d in range(3)]
    rho = torch.zeros(res, res, res, dtype=means.dtype)
    rhoc = torch.zeros(res, res, res, 3, dtype=means.dtype)
    rows = []
    for z0 in range(0, res, block):
        for y0 in range(0, res, block):
            for x0 in range(0, res, block):
                zs, ys, xs = axes[2][z0 : z0 + block], axes[1][y0 : y0 + block], axes[0][x0 : x0 + block]
                blo = torch.stack([xs[0], ys[0], zs[0]])
                bhi = torch.stack([xs[-1], ys[-1], zs[-1]])
                near = ((means + ext[:, None] >= blo) & (means - ext[:, None] <= bhi)).all(-1)
                idx = torch.nonzero(near).squeeze(1)
                if idx.numel() == 0:
                    continue
                Z, Y, X = torch.meshgrid(zs, ys, xs, indexing="ij")
                p = torch.stack([X, Y, Z], -1).reshape(-1, 3)
                d = p[:, None, :] - means[idx][None]
                q = torch.einsum("vni,nij,vnj->vn", d, prec[idx], d)
                g = rho_i[idx][None] * torch.exp(-0.5 * q)
                rows.append(((z0, y0, x0), g.sum(1), g @ colors[idx], (len(zs), len(ys), len(xs))))
    for (z0, y0, x0), r, rc, (nz, ny, nx) in rows:
        rho = rho.index_put((torch.arange(z0, z0 + nz)[:, None, None], torch.arange(y0, y0 + ny)[None, :, None],
                             torch.arange(x0, x0 + nx)[None, None, :]), r.reshape(nz, ny, nx))  # fmt: skip
        rhoc = rhoc.index_put((torch.arange(z0, z0 + nz)[:, None, None], torch.arange(y0, y0 + ny)[None, :, None],
                               torch.arange(x0, x0 + nx)[None, None, :]), rc.reshape(nz, ny, nx, 3))  # fmt: skip
    return rho, rhoc


def _grid_field(mi, dr, lo, hi):
    """Field from two gridvolumes; returns (volumes, set_data, field)."""
    to_world = (
        mi.ScalarTransform4f().translate(mi.ScalarPoint3f(lo.tolist())).scale(mi.ScalarPoint3f((hi - lo).tolist()))
    )
    vols = {}
    for name, ch in (("rho", 1), ("rhoc", 3)):
        vols[name] = mi.load_dict({"type": "gridvolume", "grid": mi.VolumeGrid(torch.zeros(2, 2, 2, ch).numpy()),
                                   "to_world": to_world, "filter_type": "trilinear"})  # fmt: skip
    params = {n: mi.traverse(v) for n, v in vols.items()}

    def set_data(rho, rhoc):
        params["rho"]["data"] = rho
        params["rhoc"]["data"] = rhoc
        params["rho"].update()
        params["rhoc"].update()

    def field(x):
        it = dr.zeros(mi.Interaction3f)
        it.p = x
        return vols["rho"].eval_1(it), mi.Color3f(vols["rhoc"].eval(it))

    return set_data, field


def _analytic_field(mi, dr, n: int):
    """Field from the mixture itself; returns (set_data, field). Unrolled over ``n`` Gaussians."""
    store = {}

    def set_data(mu, prec, rho_i, col):
        # flat storage of the tensors dr.wrap hands over (gathers index flat arrays)
        store.update(mu=mu.array, prec=prec.array, rho=rho_i.array, col=col.array)

    def field(x):
        rho = mi.Float(0.0)
        rhoc = mi.Color3f(0.0)
        for i in range(n):
            g = lambda a, j, i=i, w=1: dr.gather(mi.Float, a, i * w + j)  # noqa: E731
            dx = x.x - g(store["mu"], 0, w=3)
            dy = x.y - g(store["mu"], 1, w=3)
            dz = x.z - g(store["mu"], 2, w=3)
            P = [g(store["prec"], j, w=6) for j in range(6)]  # xx, yy, zz, xy, xz, yz
            q = (
                P[0] * dx * dx
                + P[1] * dy * dy
                + P[2] * dz * dz
                + 2 * (P[3] * dx * dy + P[4] * dx * dz + P[5] * dy * dz)
            )
            w = g(store["rho"], 0) * dr.exp(-0.5 * q)
            rho += w
            rhoc += w * mi.Color3f(g(store["col"], 0, w=3), g(store["col"], 1, w=3), g(store["col"], 2, w=3))
        return rho, rhoc

    return set_data, field


def _field_builder(means, quats, scales, opacities, mode: str, resolution: int, lo, hi, density_from: str):
    """colours [N, 3] -> the field arrays the integrator reads: a density and radiance grid, or
    the Gaussians' means, precisions, densities and colours (analytic)."""
    if mode == "grid":

        def grid_inputs(c):
            rho, rhoc = build_grid(
                means.float(),
                quats.float(),
                scales.float(),
                opacities.float(),
                c.float(),
                resolution,
                lo.float(),
                hi.float(),
                density_from=density_from,
            )
            return (rho[..., None].contiguous(), rhoc.contiguous())

        return grid_inputs
    M = covariance_factor(quats, scales)
    P = torch.linalg.inv(M @ M.transpose(-1, -2))
    prec = torch.stack([P[:, 0, 0], P[:, 1, 1], P[:, 2, 2], P[:, 0, 1], P[:, 0, 2], P[:, 1, 2]], -1)
    rho_i = density_scale(opacities, scales, density_from)

    def analytic_inputs(c):
        return tuple(x.float().reshape(-1).contiguous() for x in (means, prec, rho_i, c))

    return analytic_inputs


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    background: Tensor | None = None,
    outputs: Sequence[str] = ("rgb", "alpha"),
    mode: str = "grid",
    steps: int = 128,
    resolution: int = 64,
    spp: int = 16,
    seed: int = 0,
    density_from: str = "geomean",
) -> RenderOutput:
    """Emission-absorption render with the same call shape as ``renderers.splat.rasterize``."""
    if mode not in ("grid", "analytic"):
        raise ValueError(f"mode: expected 'grid' or 'analytic', got {mode!r}")
    if sh_degree not in (None, 0):
        raise ValueError(f"sh_degree: the volume reference evaluates plain colours only (degree 0), got {sh_degree}")
    N = means.shape[0]
    if mode == "analytic" and N > MAX_ANALYTIC:
        raise ValueError(f"mode: 'analytic' is unrolled over Gaussians, at most {MAX_ANALYTIC}; got {N} (use 'grid')")
    mi, dr = import_mitsuba()

    cols = colors if sh_degree is None else (colors[:, 0, :] * 0.28209479177387814 + 0.5).clamp_min(0)
    lo, hi = scene_box(means, scales)
    from ._volume_integrator import GaussianVolumeIntegrator

    ones = torch.ones_like(cols)
    field_inputs = _field_builder(means, quats, scales, opacities, mode, resolution, lo, hi, density_from)

    def renderer(cam: dict, seed_i: int):
        """A torch-callable, differentiable render with its own integrator and field: Dr.Jit
        replays a render in its backward pass, so no two renders may share state."""
        integ = GaussianVolumeIntegrator(mi.Properties())
        integ.steps = steps
        integ.lo, integ.hi = mi.ScalarPoint3f(lo.tolist()), mi.ScalarPoint3f(hi.tolist())
        set_data, integ.field = _grid_field(mi, dr, lo, hi) if mode == "grid" else _analytic_field(mi, dr, N)
        scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(mi, cam, spp)})

        @dr.wrap(source="torch", target="drjit")
        def render(*xs):
            set_data(*xs)
            # mi.render differentiates with respect to what its SceneParameters hold: ours are the
            # field's own arrays (not scene nodes), so wrap them directly (flags 0, no node)
            attached = mi.SceneParameters({f"field.{j}": (x, None, None, 0) for j, x in enumerate(xs)})
            return mi.render(scene, params=attached, integrator=integ, spp=spp, seed=seed_i)

        return render

    cams = mitsuba_cameras(viewmats.float(), Ks.float(), width, height)
    want_alpha = "alpha" in outputs or background is not None
    rgbs, alphas = [], []
    colour_field = field_inputs(cols)  # built once, shared by the cameras
    unit_field = field_inputs(ones) if want_alpha else None  # unit colour: that image is exactly 1 - T
    for i, cam in enumerate(cams):
        rgbs.append(renderer(cam, seed + i)(*colour_field))
        if unit_field is not None:
            alphas.append(renderer(cam, seed + i)(*unit_field)[..., :1])
    rgb = torch.stack(rgbs).to(means.dtype)
    alpha = torch.stack(alphas).to(means.dtype) if alphas else None
    if background is not None:
        rgb, _, _ = finish_images(rgb, 1 - alpha, None, background)
    return RenderOutput(rgb=rgb if "rgb" in outputs else None, alpha=alpha if "alpha" in outputs else None)
