"""Open any supported scene: detect its format from the files present and call its loader.

Above the loaders (``llff``, ``blender``, ``colmap_scene``), which share ``dataset`` below them.
"""

from __future__ import annotations

from pathlib import Path

from .blender import load_blender
from .colmap import find_colmap_model
from .colmap_scene import load_colmap
from .dataset import DEFAULT_SPLIT_EVERY, IMAGE_SUFFIXES, SceneDataset
from .errors import DatasetError
from .llff import load_llff


def detect_format(path: str | Path) -> str:
    """The format of a scene path; DatasetError naming it when none fits.

    * 'llff': a folder with ``poses_bounds.npy`` (or that file);
    * 'blender': ``transforms*.json`` (Blender, nerfstudio, ``stochastic-fields prepare``), a
      folder holding one or the file itself;
    * 'colmap': a folder with a complete COLMAP model (``sparse/0``, ``sparse``,
      ``colmap/sparse/0`` or the folder itself: cameras, images, points3D) and its ``images/``.

    A folder of photos without poses gets an error that says to run ``stochastic-fields prepare``.
    """
    path = Path(path)
    if path.is_file() and path.suffix == ".json":
        return "blender"
    if path.is_file() and path.name == "poses_bounds.npy":
        return "llff"
    if not path.exists():
        raise DatasetError(path, "dataset path does not exist")
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    if any(path.glob("transforms*.json")):
        return "blender"
    if path.is_dir() and find_colmap_model(path) is not None:
        return "colmap"
    hint = ""
    for folder in (path, path / "images"):
        photos = [p for p in (folder.iterdir() if folder.is_dir() else []) if p.suffix.lower() in IMAGE_SUFFIXES]
        if photos:
            hint = (f"; {folder} holds {len(photos)} photos without camera poses: run "
                    f"`stochastic-fields prepare {folder} --out SCENE_DIR` first (structure from motion)")
            break
    raise DatasetError(path, "unknown dataset format: expected poses_bounds.npy (LLFF), transforms*.json "
                       "(Blender/nerfstudio) or a COLMAP model (sparse/0/{cameras,images,points3D}.bin with "
                       f"images/){hint}")


def load_dataset(
    path: str | Path,
    *,
    images: str | int | None = None,
    split_every: int = DEFAULT_SPLIT_EVERY,
    downscale: int = 1,
    **kwargs,
) -> SceneDataset:
    """Load a scene, autodetecting the format (:func:`detect_format`).

    Args:
        path: an LLFF scene folder (``poses_bounds.npy``), a folder with ``transforms*.json``,
            one ``transforms*.json`` file, or a COLMAP capture (model + ``images/``).
        images: LLFF only: the image folder name (``"images_8"``) or its factor (8). Default 8.
        split_every: views with ``index % split_every == 0`` train (LLFF, COLMAP, single
            transforms.json).
        downscale: Blender/nerfstudio/COLMAP: integer downscale factor (reads ``images_<d>/``
            where present, else area-resizes; lego 800x800 -> 100x100 with 8).
        **kwargs: passed to :func:`~stochastic_fields.data.llff.load_llff`,
            :func:`~stochastic_fields.data.blender.load_blender` or
            :func:`~stochastic_fields.data.colmap_scene.load_colmap`.
    """
    kind = detect_format(path)
    path = Path(path)
    if kind == "llff":
        if downscale != 1:
            raise DatasetError(path, f"LLFF scenes pick a resolution with images=..., not downscale={downscale}")
        root = path.parent if path.is_file() else path
        return load_llff(root, images=8 if images is None else images, split_every=split_every, **kwargs)
    if images is not None:
        raise DatasetError(path, f"{kind} scenes take downscale=..., not images={images!r}")
    if kind == "colmap":
        return load_colmap(path, downscale=downscale, split_every=split_every, **kwargs)
    return load_blender(path, downscale=downscale, split_every=split_every, **kwargs)


