"""The embedded default scene: a few coloured solids on a checkered ground, ray-cast exactly.

No downloads: the meshes come from trimesh primitives, the pictures from Open3D's
``RaycastingScene`` with one ray per pixel centre (the same rays
:func:`~stochastic_fields.cameras.generate_rays` makes), so images and depth maps agree with the
package's camera conventions exactly.

Scene (world z up, units of metres-ish): a 4 x 4 ground plane at z = 0 with a checker texture,
a red box, a blue sphere, a green cylinder and a yellow torus inside ``|x|, |y| < 1.1``,
``z < 0.8``. Shading is view-independent Lambert plus ambient,
``rgb = albedo * (AMBIENT + (1 - AMBIENT) * max(0, n . l))`` with one directional light; rays
that miss show a white background and get depth 0.

Cameras: a ring on the upper hemisphere around the scene centre, looking at it, elevations
alternating between two heights, OpenCV intrinsics with a centred principal point.

Files written into ``out_dir`` (each atomically, tmp + ``os.replace``; ``transforms.json`` last,
so its presence means the scene is complete):

* ``images/frame_XXX.png``: 8-bit RGB.
* ``depth/frame_XXX.npy``: float32 [H, W] camera-z depth, 0 where the ray hits nothing.
* ``scene.ply``: the meshes with face colours (ground-truth surface).
* ``transforms.json``: nerfstudio layout, OpenGL camera-to-world ``transform_matrix``,
  ``fl_x/fl_y/cx/cy/w/h``, per-frame ``depth_file_path``, plus hints ``near``/``far``
  (camera-z), ``aabb`` ([2, 3], the mesh bounds padded by 5% of their largest extent), ``background``, ``split_every``.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import trimesh

from ..cameras import generate_rays, make_cameras, opencv_w2c_to_opengl_c2w
from .dataset import pad_box

#: Share of light that reaches every surface regardless of orientation.
AMBIENT: float = 0.35
#: Direction towards the light (normalised at use).
LIGHT_DIRECTION: tuple[float, float, float] = (0.45, -0.35, 0.82)
#: Background colour of rays that miss.
BACKGROUND: tuple[float, float, float] = (1.0, 1.0, 1.0)
#: Scene centre the cameras look at.
LOOK_AT: tuple[float, float, float] = (0.0, 0.0, 0.3)
#: Recommended training split: every 5th view (docs/definitions.md §7, about 20% of the views).
SPLIT_EVERY: int = 5
#: Relative margin of the near/far hints around the observed depth range.
_DEPTH_MARGIN: float = 0.1
#: Padding of the aabb hint around the mesh bounds, a share of their largest extent (``pad_box``).
_AABB_PADDING: float = 0.05


# ---------------------------------------------------------------------------- geometry
def _ground(rng: np.random.Generator, size: float = 4.0, cells: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checkered ground plane z = 0: vertices [(c+1)^2, 3], faces [2 c^2, 3], face colours [2 c^2, 3]."""
    xs = np.linspace(-size / 2, size / 2, cells + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    light = np.array([0.85, 0.83, 0.78]) + rng.uniform(-0.05, 0.05, 3)
    dark = np.array([0.35, 0.42, 0.50]) + rng.uniform(-0.05, 0.05, 3)
    faces, colours = [], []
    for i in range(cells):
        for j in range(cells):
            a, b = i * (cells + 1) + j, (i + 1) * (cells + 1) + j
            faces += [[a, b, b + 1], [a, b + 1, a + 1]]  # counter-clockwise seen from +z
            colour = light if (i + j) % 2 == 0 else dark
            colours += [colour, colour]
    return vertices, np.asarray(faces), np.clip(np.asarray(colours), 0.0, 1.0)


def scene_mesh(seed: int = 0) -> trimesh.Trimesh:
    """The synthetic scene as one trimesh with per-face colours (``visual.face_colors``, uint8 RGBA)."""
    rng = np.random.default_rng(seed)
    parts: list[tuple[trimesh.Trimesh, np.ndarray]] = []
    gv, gf, gc = _ground(rng)
    parts.append((trimesh.Trimesh(gv, gf, process=False), gc))

    def place(mesh: trimesh.Trimesh, xyz: tuple[float, float, float]) -> trimesh.Trimesh:
        mesh.apply_translation(xyz)
        return mesh

    box = place(trimesh.creation.box(extents=(0.55, 0.55, 0.55)), (-0.6, -0.45, 0.275))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.5, (0, 0, 1), point=(-0.6, -0.45, 0.0)))
    sphere = place(trimesh.creation.icosphere(subdivisions=3, radius=0.35), (0.55, -0.35, 0.35))
    cylinder = place(trimesh.creation.cylinder(radius=0.22, height=0.8, sections=32), (0.05, 0.65, 0.4))
    torus = place(trimesh.creation.torus(major_radius=0.3, minor_radius=0.09, major_sections=32, minor_sections=12),
                  (-0.65, 0.55, 0.09))
    palette = {
        "box": (0.85, 0.18, 0.15),
        "sphere": (0.15, 0.35, 0.85),
        "cylinder": (0.2, 0.7, 0.25),
        "torus": (0.95, 0.8, 0.15),
    }
    for name, mesh in (("box", box), ("sphere", sphere), ("cylinder", cylinder), ("torus", torus)):
        base = np.asarray(palette[name])
        # a little per-face variation gives the field texture to learn
        jitter = rng.uniform(-0.06, 0.06, size=(len(mesh.faces), 1))
        parts.append((mesh, np.clip(base[None] + jitter, 0.0, 1.0)))

    vertices, faces, colours, offset = [], [], [], 0
    for mesh, col in parts:
        vertices.append(np.asarray(mesh.vertices))
        faces.append(np.asarray(mesh.faces) + offset)
        colours.append(col)
        offset += len(mesh.vertices)
    out = trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)
    rgba = np.concatenate([np.round(np.concatenate(colours) * 255), np.full((len(out.faces), 1), 255)], 1)
    out.visual.face_colors = rgba.astype(np.uint8)
    return out


# ---------------------------------------------------------------------------- cameras
def ring_cameras(
    num_views: int,
    width: int,
    height: int,
    *,
    radius: float = 3.2,
    elevations_deg: tuple[float, float] = (25.0, 45.0),
    fov_x_deg: float = 55.0,
    seed: int = 0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(K [V, 3, 3], OpenCV world-to-camera [V, 4, 4]) on an upper-hemisphere ring around LOOK_AT.

    View v sits at azimuth ``phase + 2 pi v / V`` and alternates between the two elevations;
    it looks at LOOK_AT with x right, y down (world z up).
    """
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, 2.0 * math.pi)
    target = np.asarray(LOOK_AT)
    up = np.array([0.0, 0.0, 1.0])
    w2c = np.zeros((num_views, 4, 4))
    for v in range(num_views):
        az = phase + 2.0 * math.pi * v / num_views
        el = math.radians(elevations_deg[v % 2])
        centre = target + radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        forward = target - centre
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R_c2w = np.stack([right, down, forward], axis=1)
        w2c[v, :3, :3] = R_c2w.T
        w2c[v, :3, 3] = -R_c2w.T @ centre
        w2c[v, 3, 3] = 1.0
    fx = 0.5 * width / math.tan(0.5 * math.radians(fov_x_deg))
    K = np.array([[fx, 0.0, width / 2.0], [0.0, fx, height / 2.0], [0.0, 0.0, 1.0]])
    return torch.from_numpy(np.repeat(K[None], num_views, 0)), torch.from_numpy(w2c)


# ---------------------------------------------------------------------------- rendering
def render_views(mesh: trimesh.Trimesh, cameras, *, nthreads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast every pixel centre: (rgb [V, H, W, 3] float32 in [0, 1], camera-z depth [V, H, W]).

    Depth is ``t_hit * z_scale`` (t_hit along unit directions), 0 where the ray misses; colour
    is Lambert + ambient of the hit face's colour with the normal turned towards the camera.
    """
    import open3d as o3d  # imported here: at import time it announces itself inside Jupyter

    rays = generate_rays(cameras, 0.0, 1.0, bounds="ray_distance")  # [V, H, W]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    o = rays.origins.double().numpy()
    d = rays.directions.double().numpy()
    cast = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], -1).astype(np.float32)), nthreads=nthreads)
    t_hit = cast["t_hit"].numpy().astype(np.float64)  # [V, H, W], inf on miss
    prim = cast["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t_hit)
    normals = cast["primitive_normals"].numpy().astype(np.float64)
    facing = np.sum(normals * d, axis=-1, keepdims=True) > 0
    normals = np.where(facing, -normals, normals)  # two-sided
    light = np.asarray(LIGHT_DIRECTION) / np.linalg.norm(LIGHT_DIRECTION)
    shade = AMBIENT + (1.0 - AMBIENT) * np.clip(normals @ light, 0.0, None)
    albedo = np.asarray(mesh.visual.face_colors)[:, :3].astype(np.float64) / 255.0
    rgb = np.empty(t_hit.shape + (3,))
    rgb[...] = BACKGROUND
    rgb[hit] = albedo[prim[hit]] * shade[hit][:, None]
    depth = np.where(hit, np.where(hit, t_hit, 0.0) * rays.z_scale.double().numpy(), 0.0)
    return rgb.astype(np.float32), depth.astype(np.float32)


# ---------------------------------------------------------------------------- files
def _atomic_write(path: Path, write) -> None:
    """Call ``write(tmp_path)`` then move the temporary file onto ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def make_synthetic_scene(
    out_dir: str | Path,
    *,
    num_views: int = 40,
    width: int = 96,
    height: int = 72,
    seed: int = 0,
) -> Path:
    """Generate the synthetic scene into ``out_dir`` (see the module docstring) and return it.

    The defaults (40 views of 96 x 72) render in well under a second on one CPU core.
    Load it back with :func:`~stochastic_fields.data.load_dataset`.
    """
    if num_views < 2 or width < 2 or height < 2:
        raise ValueError(f"need num_views >= 2 and an image of at least 2x2, got {num_views} views of {width}x{height}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mesh = scene_mesh(seed)
    K, w2c = ring_cameras(num_views, width, height, seed=seed)
    cameras = make_cameras(K, w2c, height, width)  # float64: exact ray geometry
    rgb, depth = render_views(mesh, cameras)
    c2w_gl = opencv_w2c_to_opengl_c2w(w2c).numpy()

    frames = []
    for v in range(num_views):
        img_rel, depth_rel = f"images/frame_{v:03d}.png", f"depth/frame_{v:03d}.npy"
        image8 = np.round(np.clip(rgb[v], 0.0, 1.0) * 255).astype(np.uint8)
        _atomic_write(out / img_rel, lambda p, a=image8: iio.imwrite(p, a, extension=".png"))
        _atomic_write(out / depth_rel, lambda p, a=depth[v]: np.save(p, a, allow_pickle=False))
        frames.append({"file_path": img_rel, "depth_file_path": depth_rel, "transform_matrix": c2w_gl[v].tolist()})
    _atomic_write(out / "scene.ply", lambda p: mesh.export(p, file_type="ply"))

    valid = depth[depth > 0]
    box = pad_box(torch.tensor(mesh.bounds[0]), torch.tensor(mesh.bounds[1]), _AABB_PADDING)
    meta = {
        "camera_model": "OPENCV",
        "fl_x": float(K[0, 0, 0]),
        "fl_y": float(K[0, 1, 1]),
        "cx": float(K[0, 0, 2]),
        "cy": float(K[0, 1, 2]),
        "w": width,
        "h": height,
        "near": float(valid.min() * (1.0 - _DEPTH_MARGIN)),
        "far": float(valid.max() * (1.0 + _DEPTH_MARGIN)),
        "aabb": box.tolist(),
        "background": list(BACKGROUND),
        "split_every": SPLIT_EVERY,
        "seed": seed,
        "frames": frames,
    }
    _atomic_write(out / "transforms.json", lambda p: p.write_text(json.dumps(meta, indent=1)))
    return out
