"""The region of space a field models, and its map to the unit cube [-1, 1]^3.

"Model only what a scene needs": the field's capacity, the random KL points and the
occupancy grid all live in this region, fitted from the cameras, their near/far bounds and
(when present) sparse points.

Two parametrisations:

* ``aabb``: an axis-aligned box in world coordinates, mapped linearly:
  ``u = 2 (x - lo) / (hi - lo) - 1``. For bounded, object-centric scenes.
* ``ndc``: forward-facing scenes (LLFF). Points are expressed in a reference camera (OpenCV,
  z forward) and mapped to normalised device coordinates
  ``(x / (z tan_x), y / (z tan_y), 1 - 2 near / z)``, then linearly into the fitted box of
  those coordinates. Resolution is spent uniformly in image space and in disparity, which is
  where forward-facing captures carry information. All products stay metric: this map only
  decides where the field's parameters live.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class SceneRegion(nn.Module):
    """Maps world points [*B, 3] to unit coordinates [*B, 3] in [-1, 1]^3 and back.

    Buffers:
        kind_code: 0 for aabb, 1 for ndc.
        box: [2, 3] lower/upper corners of the box, in world (aabb) or NDC (ndc) coordinates.
        ref_w2c: [4, 4] reference world-to-camera transform (identity for aabb).
        ndc_scale: [3] (tan_x, tan_y, near) of the reference camera (ones for aabb).
    """

    def __init__(self, kind: str, box: Tensor, ref_w2c: Tensor | None = None, ndc_scale: Tensor | None = None):
        super().__init__()
        if kind not in ("aabb", "ndc"):
            raise ValueError(f"SceneRegion kind must be 'aabb' or 'ndc', got {kind!r}")
        box = torch.as_tensor(box, dtype=torch.float32)
        if box.shape != (2, 3) or not bool(torch.all(box[1] > box[0])):
            raise ValueError(f"SceneRegion box must be [2, 3] with max > min per axis, got {box.tolist()}")
        self.register_buffer("kind_code", torch.tensor(0 if kind == "aabb" else 1))
        self.register_buffer("box", box.clone())
        self.register_buffer("ref_w2c", torch.eye(4) if ref_w2c is None else torch.as_tensor(ref_w2c, dtype=torch.float32).clone())
        self.register_buffer("ndc_scale", torch.ones(3) if ndc_scale is None else torch.as_tensor(ndc_scale, dtype=torch.float32).clone())

    @property
    def kind(self) -> str:
        return "aabb" if int(self.kind_code) == 0 else "ndc"

    # ----------------------------------------------------------------- world <-> intermediate
    def _to_box_coords(self, points: Tensor) -> Tensor:
        if self.kind == "aabb":
            return points
        R, t = self.ref_w2c[:3, :3].to(points), self.ref_w2c[:3, 3].to(points)
        cam = points @ R.T + t
        tan_x, tan_y, near = self.ndc_scale.to(points).unbind()
        z = cam[..., 2].clamp_min(near * 1e-3)
        return torch.stack([cam[..., 0] / (z * tan_x), cam[..., 1] / (z * tan_y), 1.0 - 2.0 * near / z], dim=-1)

    def _from_box_coords(self, coords: Tensor) -> Tensor:
        if self.kind == "aabb":
            return coords
        tan_x, tan_y, near = self.ndc_scale.to(coords).unbind()
        z = 2.0 * near / (1.0 - coords[..., 2]).clamp_min(1e-6)
        cam = torch.stack([coords[..., 0] * z * tan_x, coords[..., 1] * z * tan_y, z], dim=-1)
        R, t = self.ref_w2c[:3, :3].to(coords), self.ref_w2c[:3, 3].to(coords)
        return (cam - t) @ R

    # ----------------------------------------------------------------- public maps
    def to_unit(self, points: Tensor) -> Tensor:
        """[*B, 3] world -> [*B, 3] unit coordinates (inside the region iff all in [-1, 1])."""
        c = self._to_box_coords(points)
        lo, hi = self.box[0].to(c), self.box[1].to(c)
        return 2.0 * (c - lo) / (hi - lo) - 1.0

    def from_unit(self, unit: Tensor) -> Tensor:
        """[*B, 3] unit coordinates -> [*B, 3] world points."""
        lo, hi = self.box[0].to(unit), self.box[1].to(unit)
        return self._from_box_coords(lo + (unit + 1.0) * 0.5 * (hi - lo))

    def contains(self, points: Tensor) -> Tensor:
        """[*B] bool: the point lies inside the modelled region."""
        return (self.to_unit(points).abs() <= 1.0).all(dim=-1)

    def sample_stratified(self, points_per_axis: int, generator: torch.Generator | None = None) -> Tensor:
        """[n^3, 3] world points: one uniform draw in each cell of an n x n x n partition of the region.

        This is the paper's random-point scheme (appendix, "The posterior-prior KL divergence"):
        each axis split into n evenly spaced bins, a uniform draw inside each bin.
        """
        n = points_per_axis
        device = self.box.device
        idx = torch.stack(torch.meshgrid(*(torch.arange(n, device=device),) * 3, indexing="ij"), dim=-1).reshape(-1, 3)
        jitter = torch.rand(idx.shape, generator=generator, device=device)
        unit = (idx + jitter) / n * 2.0 - 1.0
        return self.from_unit(unit)

    def cell_length(self, resolution: tuple[int, int, int]) -> float:
        """World length of one cell of an (X, Y, Z) = ``resolution`` grid over the unit cube, at
        the region's centre: the geometric mean of its three edges,

            L = (prod_i |d from_unit / d u_i|(0) * 2 / res_i)^(1/3)

        (a box: L = (prod_i (hi_i - lo_i) / res_i)^(1/3); NDC: the cell at the centre of the
        fitted NDC box, whose edges grow with depth). Scales with the scene's unit of length, so
        a density counted per L (``field.density_per='cell'``) does not depend on it. The
        derivatives are central differences in float64 (exact for a box)."""
        if len(resolution) != 3 or any(int(r) < 1 for r in resolution):
            raise ValueError(f"resolution must be three positive integers, got {resolution!r}")
        h = 1e-3
        step = h * torch.eye(3, dtype=torch.float64, device=self.box.device)
        world = self.from_unit(torch.cat([step, -step]))  # the buffers follow the probe's dtype
        res = torch.tensor([float(r) for r in resolution], dtype=torch.float64, device=self.box.device)
        edges = (world[:3] - world[3:]).norm(dim=-1) / (2 * h) * 2.0 / res  # [3]
        return float(edges.log().mean().exp())

    def extra_repr(self) -> str:
        return f"kind={self.kind}, box={self.box.tolist()}"


def random_unit_directions(n: int, generator: torch.Generator | None = None, device=None) -> Tensor:
    """[n, 3] directions uniform on the sphere (normalised Gaussian draws)."""
    d = torch.randn(n, 3, generator=generator, device=device)
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _average_w2c(w2c: Tensor) -> Tensor:
    """[4, 4] world-to-camera transform of the 'mean' camera: mean centre, mean axes re-orthonormalised."""
    c2w = torch.linalg.inv(w2c.double())
    centre = c2w[:, :3, 3].mean(0)
    R_mean = c2w[:, :3, :3].mean(0)
    U, _, Vh = torch.linalg.svd(R_mean)
    R = U @ Vh
    if torch.det(R) < 0:
        U[:, -1] = -U[:, -1]
        R = U @ Vh
    avg_c2w = torch.eye(4, dtype=torch.float64)
    avg_c2w[:3, :3] = R
    avg_c2w[:3, 3] = centre
    return torch.linalg.inv(avg_c2w).float()


def frustum_points(intrinsics: Tensor, w2c: Tensor, height: int, width: int, near: Tensor, far: Tensor,
                   grid: int = 9, depths: int = 16) -> Tensor:
    """[V * grid^2 * depths, 3] world points filling every camera's frustum between near and far.

    Shapes: intrinsics [V, 3, 3] (or 4x4), w2c [V, 4, 4], near/far [V]. Depths are spaced
    linearly in disparity, the spacing forward-facing captures resolve.
    """
    V = w2c.shape[0]
    dev = w2c.device
    u = torch.linspace(0.0, float(width), grid, device=dev)
    v = torch.linspace(0.0, float(height), grid, device=dev)
    uu, vv = torch.meshgrid(u, v, indexing="xy")
    pix = torch.stack([uu.reshape(-1), vv.reshape(-1), torch.ones(grid * grid, device=dev)], -1)  # [G, 3]
    K = intrinsics[:, :3, :3].float()
    rays_cam = pix[None] @ torch.linalg.inv(K).transpose(1, 2)  # [V, G, 3] with z = 1
    s = torch.linspace(0.0, 1.0, depths, device=dev)
    disp = (1.0 / near[:, None]) * (1 - s) + (1.0 / far[:, None]) * s  # [V, D]
    z = 1.0 / disp
    cam = rays_cam[:, :, None, :] * z[:, None, :, None]  # [V, G, D, 3]
    c2w = torch.linalg.inv(w2c.float())
    world = cam.reshape(V, -1, 3) @ c2w[:, :3, :3].transpose(1, 2) + c2w[:, None, :3, 3]
    return world.reshape(-1, 3)


def fit_region(intrinsics: Tensor, w2c: Tensor, height: int, width: int, near: Tensor, far: Tensor, *,
               forward_facing: bool, aabb: Tensor | None = None, padding: float = 0.05) -> SceneRegion:
    """The modelled region of a scene.

    * object-centric (``forward_facing=False``): the scene box ``aabb`` the loaders fit
      (``data.dataset.fit_scene_aabb``: cameras, near/far and sparse points), mapped linearly.
    * forward-facing: NDC of the average camera; its box covers the frustum points of every
      camera (1st-99th percentiles per axis, padded), so no capacity is spent on the thin
      slivers only one extreme corner ray reaches.
    """
    if not forward_facing:
        if aabb is None:
            raise ValueError("fit_region: an object-centric scene needs its aabb (see data.dataset.fit_scene_aabb)")
        return SceneRegion("aabb", torch.as_tensor(aabb, dtype=torch.float32))
    near = torch.as_tensor(near, dtype=torch.float32).reshape(-1).expand(w2c.shape[0])
    far = torch.as_tensor(far, dtype=torch.float32).reshape(-1).expand(w2c.shape[0])
    if not bool(torch.all(far > near)):
        raise ValueError(f"fit_region needs far > near for every camera, got near={near.tolist()} far={far.tolist()}")
    pts = frustum_points(intrinsics, w2c, height, width, near, far)
    ref = _average_w2c(w2c)
    K = intrinsics[0, :3, :3].float()
    tan_x, tan_y = width / (2.0 * K[0, 0]), height / (2.0 * K[1, 1])
    ndc_scale = torch.tensor([float(tan_x), float(tan_y), float(near.min()) * 0.9])
    probe = SceneRegion("ndc", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), ref, ndc_scale)
    coords = probe._to_box_coords(pts)
    lo = torch.quantile(coords, 0.01, dim=0)
    hi = torch.quantile(coords, 0.99, dim=0)
    hi[2] = torch.clamp(coords[:, 2].max(), max=1.0 - 1e-4)
    lo[2] = coords[:, 2].min()
    pad = (hi - lo) * padding
    lo, hi = lo - pad, hi + pad
    hi[2] = torch.clamp(hi[2], max=1.0 - 1e-4)
    return SceneRegion("ndc", torch.stack([lo, hi]), ref, ndc_scale)
