"""Virtual cameras between neighbouring training views, and patches of rays through them.

Two users: the depth calibration renders its calibration views here (halfway between each
training view and its nearest neighbour, ``calibration.calibration_views``), and the unseen-view
depth smoothness regulariser (``loss.lambda_smoothness``, ``depth_smoothness``) draws small patches
of rays from a pool of such cameras at several fractions of the way. Both stay among the training
viewpoints, as the novel views a user renders do, and neither reads a test view.

A virtual camera between views i and j at fraction f (0: view i, 1: view j):

    centre    c = o + (c_i - o)(1 - f) + (c_j - o) f, rescaled to |c - o| = (1 - f)|c_i - o| + f|c_j - o|
    rotation  R = slerp(R_i, R_j; f)
    K, size   view i's
    bounds    the pair's widest (min near, max far), or interpolated at f

with o the centre of the scene box: the centre moves on the arc around o (orbits stay outside the
scene; a forward-facing capture, far from o, moves by a negligible amount off the chord).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp
from torch import Tensor

from .cameras import camera_centres, generate_rays, intrinsics_3x3, make_cameras, select_cameras
from .rays import RayBundle

#: A virtual view's render bounds from its pair's: "widest" (the nearer near, the farther far) or
#: "interpolated" (both at the view's fraction).
BOUNDS_CHOICES: tuple[str, ...] = ("widest", "interpolated")
#: Fractions of the way between two training views the smoothness patches' cameras sit at.
PATCH_FRACTIONS: tuple[float, ...] = (0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875)
#: Nearest training neighbours each training view is paired with for the smoothness patches.
PATCH_NEIGHBOURS: int = 2


def views_between(dataset, *, neighbours: int, fractions: tuple[float, ...], bounds: str,
                  what: str = "virtual views") -> tuple[object, Tensor, Tensor, list[tuple[int, int]]]:
    """Virtual cameras between each training view and its ``neighbours`` nearest other training
    views (camera centres), at each of ``fractions`` of the way (module doc). Returns (cameras
    [P], near [P], far [P], the (i, j) view pair of each camera), the pairs (i < j) sorted and each
    pair's fractions in the given order. ``what``: the cameras' name in the errors."""
    train = list(dataset.train_indices)
    if len(train) < 2:
        raise ValueError(f"{dataset.root}: {what} need at least 2 training views, got {len(train)}")
    if neighbours < 1:
        raise ValueError(f"{what} need neighbours >= 1, got {neighbours}")
    if bounds not in BOUNDS_CHOICES:
        raise ValueError(f"{what}' bounds must be one of {BOUNDS_CHOICES}, got {bounds!r}")
    if not fractions or not all(0.0 < float(f) < 1.0 for f in fractions):
        raise ValueError(f"{what}' fractions must lie strictly between 0 and 1, got {tuple(fractions)}")
    centres = camera_centres(dataset.cameras).double()[train]
    dist = torch.cdist(centres, centres)
    dist.fill_diagonal_(float("inf"))
    nearest = dist.argsort(dim=1)[:, :min(neighbours, len(train) - 1)]
    pairs = sorted({tuple(sorted((train[a], train[int(b)]))) for a in range(len(train)) for b in nearest[a]})
    w2c = dataset.cameras.extrinsics.double()
    K = intrinsics_3x3(dataset.cameras).double()
    o = dataset.aabb.double().mean(0)
    views, Ks, view_pairs, nears, fars = [], [], [], [], []
    for i, j in pairs:
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([w2c[i, :3, :3].numpy(), w2c[j, :3, :3].numpy()])))
        ci, cj = centres[train.index(i)] - o, centres[train.index(j)] - o
        for f in fractions:
            f = float(f)
            R = torch.from_numpy(slerp([f]).as_matrix()[0])
            direction = (1.0 - f) * ci + f * cj
            c = o + direction / direction.norm().clamp_min(1e-12) * ((1.0 - f) * ci.norm() + f * cj.norm())
            m = torch.eye(4, dtype=torch.float64)
            m[:3, :3], m[:3, 3] = R, -R @ c
            views.append(m)
            Ks.append(K[i])
            view_pairs.append((i, j))
            if bounds == "widest":
                nears.append(torch.minimum(dataset.near[i], dataset.near[j]))
                fars.append(torch.maximum(dataset.far[i], dataset.far[j]))
            else:
                nears.append((1.0 - f) * dataset.near[i] + f * dataset.near[j])
                fars.append((1.0 - f) * dataset.far[i] + f * dataset.far[j])
    cams = make_cameras(torch.stack(Ks).float(), torch.stack(views).float(), int(dataset.height), int(dataset.width))
    return cams, torch.stack(nears).float(), torch.stack(fars).float(), view_pairs


class PatchSampler:
    """Square patches of rays through a fixed pool of virtual cameras (``views_between`` at
    ``PATCH_FRACTIONS`` of the way to each training view's ``PATCH_NEIGHBOURS`` nearest neighbours,
    the pair's widest bounds): ``sample`` draws a camera and a patch position per patch.
    A dataset with one training view has no pool (``PatchSampler.for_dataset`` returns None)."""

    def __init__(self, cameras, near: Tensor, far: Tensor, height: int, width: int):
        self.cameras, self.near, self.far = cameras, near, far
        self.height, self.width = int(height), int(width)

    @classmethod
    def for_dataset(cls, dataset, device: torch.device | str = "cpu") -> "PatchSampler | None":
        """The pool of ``dataset``'s training views on ``device``; None with fewer than 2 training views."""
        if len(dataset.train_indices) < 2:
            return None
        cams, near, far, _ = views_between(dataset, neighbours=PATCH_NEIGHBOURS, fractions=PATCH_FRACTIONS,
                                           bounds="widest")
        cams = make_cameras(intrinsics_3x3(cams).to(device), cams.extrinsics.to(device), int(dataset.height),
                            int(dataset.width))
        return cls(cams, near.to(device), far.to(device), int(dataset.height), int(dataset.width))

    @property
    def num_cameras(self) -> int:
        return int(self.cameras.batch_size)

    def sample(self, num_patches: int, size: int, generator: torch.Generator) -> RayBundle:
        """RayBundle [P, size, size]: per patch a camera of the pool and a top-left pixel drawn
        uniformly (with one sub-pixel offset per patch), rays through ``size`` x ``size``
        neighbouring pixels one pixel apart (row v, column u). ``generator``: a CPU generator."""
        if size > min(self.height, self.width):
            raise ValueError(f"a smoothness patch of {size} pixels does not fit a {self.width}x{self.height} image")
        device = self.near.device
        cam = torch.randint(0, self.num_cameras, (num_patches,), generator=generator)
        corner = torch.rand(num_patches, 2, generator=generator, dtype=torch.float64)
        corner = corner * torch.tensor([self.width - size + 1.0, self.height - size + 1.0], dtype=torch.float64)
        steps = torch.arange(size, dtype=torch.float64)
        v, u = torch.meshgrid(steps, steps, indexing="ij")
        offsets = torch.stack([u, v], dim=-1).reshape(1, size * size, 2)  # (u, v), row-major
        pixels = (corner[:, None, :] + offsets).to(device=device, dtype=self.near.dtype)
        cam = cam.to(device)
        rays = generate_rays(select_cameras(self.cameras, cam), self.near[cam], self.far[cam], pixels)
        return rays.reshape(num_patches, size, size)
