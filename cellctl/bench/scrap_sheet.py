"""The picture sheet of generated scrap pieces (docs/img/scrap_pieces.png): each piece as the twin builds
it, its metal grey and its paint red, seen from behind the robot, titled with its reference, family and line.

Ray cast from the meshes themselves (Open3D's RaycastingScene on the CPU), so it runs on any machine."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.scenes import load_scene
from sim.scenes.scrap import generate, parse_ref


def _render(scene, size=(300, 260), elev_deg: float = 35.0, azim_deg: float = 200.0) -> np.ndarray:
    """An RGB image of the piece, ray cast with Open3D (every pixel one ray, Lambert shading, a grey floor)."""
    import open3d as o3d

    meshes = [(scene.object_mesh, scene.object_rgb), (scene.paint_mesh, scene.paint_rgb)]
    rs = o3d.t.geometry.RaycastingScene()
    ids = [rs.add_triangles(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)) for m, _ in meshes]
    lo, hi = scene.full_mesh.bounds
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    eye = centre + 3.2 * radius * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    w, h = size
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(fov_deg=38.0, center=centre.tolist(), eye=eye.tolist(),
                                                            up=[0, 0, 1], width_px=w, height_px=h)
    hit = rs.cast_rays(rays)
    t = hit["t_hit"].numpy()
    geom, normal = hit["geometry_ids"].numpy(), hit["primitive_normals"].numpy()
    d = rays.numpy()[..., 3:]
    light = np.array([-0.5, -0.4, 0.8]) / np.linalg.norm([-0.5, -0.4, 0.8])
    shade = 0.3 + 0.7 * np.abs(normal @ light)  # both sides lit: a thin plate's back face shows too
    img = np.ones((h, w, 3))
    # the floor: where a missed ray meets z = 0, a pale grey
    tz = np.where(d[..., 2] < 0, -eye[2] / np.where(d[..., 2] < 0, d[..., 2], -1), np.inf)
    img[np.isinf(t) & np.isfinite(tz)] = 0.93
    for gid, (_, rgb) in zip(ids, meshes):
        m = np.isfinite(t) & (geom == gid)
        img[m] = np.clip(np.asarray(rgb) * 1.3 * shade[m][:, None], 0, 1)
    return img


def write_sheet(refs: list[str], out: str | Path, cols: int = 4) -> Path:
    """One panel per reference, titled with what the generator drew."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for ref in refs:
        if parse_ref(ref) is None:
            raise ValueError(f"not a generated piece: {ref!r} (scrap:<gen_seed>:<index>)")
    rows = int(np.ceil(len(refs) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols, 2.9 * rows), dpi=110, squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, ref in zip(axes.ravel(), refs):
        _, _, meta = generate(*parse_ref(ref))
        ax.imshow(_render(load_scene(ref)))
        ax.set_title(f"{ref}\n{meta['family']}, {', '.join(meta['lines'])} ({meta['length_m']:.2f} m)", fontsize=8)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.95, wspace=0.03, hspace=0.2)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
