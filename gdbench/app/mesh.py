"""A triangle mesh of a Gaussian scene by TSDF fusion of rendered depth (docs/export.md, "Meshes").

``extract_mesh``: the scene is rendered from ``views`` cameras spread evenly over a sphere around
it (a Fibonacci lattice, each looking at the scene's centre from the distance that frames it):
colour without background divided by alpha (the colour of the surface, not of its mix with the
background), the expected depth (``renderers.splat``'s ``depth``: sum w z / alpha) and alpha.
Pixels whose alpha is at least ``alpha_min`` are fused into a truncated signed distance volume
(Open3D's ``UniformTSDFVolume``: a cube of ``resolution``^3 voxels over the scene's framed ball,
truncation 4 voxels; Open3D 0.20's ``ScalableTSDFVolume`` fused nothing here) whose
zero level set, extracted by marching cubes, is the mesh, with the fused colour per vertex.
Components with fewer than ``min_component`` of the triangles (floaters) are dropped.

This is what threestudio's and DreamGaussian's exporters offer besides a density grid; depth
fusion follows the surface the images show, so a mesh seen from the training views looks like
the renders. Open3D is an optional dependency (``pip install open3d-cpu``), imported here only.

``write_mesh`` writes the mesh as binary glTF (.glb: vertex colours in ``COLOR_0``) or Wavefront
OBJ (vertex colours after the positions, the extension MeshLab, Blender and trimesh read),
rotated to ``up`` (glTF's own convention is +Y up) and recording its up axis and run
(``core.filetags``: the glTF asset's ``extras``, the OBJ's header comment).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from gdbench.core.filetags import check_up, up_rotation
from gdbench.core.scene import GaussianScene

MESH_FORMATS = ("glb", "obj")
O3D_EXTRA = "pip install open3d-cpu (or `make setup`)"


def _import_o3d():
    try:
        import open3d as o3d
    except ImportError as e:
        raise ImportError(f"mesh export fuses depth with Open3D: {O3D_EXTRA}") from e
    return o3d


def extract_mesh(
    scene: GaussianScene,
    *,
    views: int = 64,
    size: int = 256,
    resolution: int = 192,
    alpha_min: float = 0.5,
    min_component: float = 0.01,
    device: str | torch.device = "cpu",
):
    """A ``trimesh.Trimesh`` of ``scene`` (see the module docstring), +Z up, with vertex colours.
    ``resolution``: voxels along each side of the TSDF's cube (192: 8.5 MB per million voxels of
    Open3D's float TSDF, weight and colour, about 240 MB)."""
    import trimesh

    from gdbench.core.framing import bounds, orbit_radius, sphere_cameras
    from renderers.splat import rasterize

    if not isinstance(scene, GaussianScene):
        raise TypeError(f"scene: expected a GaussianScene, got {type(scene).__name__}")
    if len(scene) == 0:
        raise ValueError("scene: has no Gaussians to mesh")
    for name, value, lo in (("views", views, 1), ("size", size, 16), ("resolution", resolution, 16)):
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise ValueError(f"{name}: expected an int >= {lo}, got {value!r}")
    if not 0 < alpha_min < 1:
        raise ValueError(f"alpha_min: expected a number in (0, 1), got {alpha_min!r}")
    o3d = _import_o3d()
    centre, radius = bounds(scene)
    fovy = 45.0
    cams = sphere_cameras(centre, orbit_radius(radius, fovy), views, size, fovy)
    side = 2.1 * radius  # the framed ball, and a margin for the truncation band
    volume = o3d.pipelines.integration.UniformTSDFVolume(
        length=side,
        resolution=resolution,
        sdf_trunc=4 * side / resolution,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8,
        origin=(centre.detach().cpu().double().numpy() - side / 2).reshape(3, 1),
    )
    s = scene.detach().to(device)
    for k in range(views):
        cam = cams[k].to(device)
        with torch.no_grad():
            out = rasterize(
                **s.render_args(),
                viewmats=cam.viewmats,
                Ks=cam.Ks,
                width=size,
                height=size,
                outputs=("rgb", "alpha", "depth"),
            )
        alpha = out.alpha[0, ..., 0].cpu()
        keep = alpha >= alpha_min
        rgb = (out.rgb[0].cpu() / alpha.clamp_min(1e-6)[..., None]).clamp(0, 1)
        depth = torch.where(keep, out.depth[0, ..., 0].cpu(), torch.zeros_like(alpha))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray((rgb.numpy() * 255).astype(np.uint8))),
            o3d.geometry.Image(np.ascontiguousarray(depth.numpy().astype(np.float32))),
            depth_scale=1.0,
            depth_trunc=1e9,
            convert_rgb_to_intensity=False,
        )
        K = cam.Ks[0].cpu().double().numpy()
        intr = o3d.camera.PinholeCameraIntrinsic(size, size, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        volume.integrate(rgbd, intr, cam.viewmats[0].cpu().double().numpy())
    m = volume.extract_triangle_mesh()
    mesh = trimesh.Trimesh(
        np.asarray(m.vertices),
        np.asarray(m.triangles),
        vertex_colors=(np.asarray(m.vertex_colors) * 255).round().astype(np.uint8),
        process=True,
    )
    if len(mesh.faces) == 0:
        raise ValueError(
            f"scene: no surface where alpha reaches {alpha_min} in any of {views} views; "
            "lower alpha_min or check the scene's opacities"
        )
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        big = [p for p in parts if len(p.faces) >= min_component * len(mesh.faces)]
        mesh = trimesh.util.concatenate(big)
    return mesh


def write_mesh(mesh, path: str | Path, *, up: str = "+y", run: str | None = None) -> Path:
    """Write a +Z-up ``mesh`` as .glb or .obj (by ``path``'s suffix), rotated so that ``up`` is up,
    atomically, recording the up axis and ``run`` (module docstring); returns the path."""
    from trimesh.exchange.gltf import export_glb
    from trimesh.exchange.obj import export_obj

    from gdbench.core.io import atomic_write, check_folder

    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ValueError(f"path: a mesh is written as .glb or .obj; got {str(path)!r}")
    check_folder(path.parent, "path")
    up = check_up(up)
    m = mesh.copy()
    if up != "+z":
        t = np.eye(4)
        t[:3, :3] = up_rotation(up).numpy()
        m.apply_transform(t)
    tags = {"up": up, "run": run}
    if fmt == "glb":

        def tag(tree: dict) -> None:
            tree.setdefault("asset", {})["extras"] = {"gdbench": tags}

        data = export_glb(m.scene(), tree_postprocessor=tag)
    else:
        data = export_obj(m, include_normals=False, include_color=True, header=f"gdbench {json.dumps(tags)}")
        data = data.encode() if isinstance(data, str) else data
    return atomic_write(path, lambda f: f.write(data))
