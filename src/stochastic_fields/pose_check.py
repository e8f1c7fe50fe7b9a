"""Training photos the trained field fits far worse than the others: a check of their poses.

Structure from motion can place a camera wrong and report nothing: on an object whose sides look
alike, a few photos can settle in a mirrored pose (the camera on the other side of the object,
turned about 180 degrees) that the photos' own verified matches support better than the right one
(docs/capture.md measures one). No geometric check of the matches tells it; the radiance field
does. One field fitted to every photo cannot agree with a photo whose camera is wrong, so that
photo keeps a colour error far above the others' after training: on lego's mirrored registration
the five affected training photos ended at 13.9-16.2 dB against a median of 24.5 dB, the next
worst at 20.4.

The check is a robust outlier test on the training views' PSNR (Iglewicz & Hoaglin 1993): with
m the median and MAD the median absolute deviation from it, a photo is flagged when

    psnr < m - max(POSE_CHECK_Z * 1.4826 * MAD, POSE_CHECK_MIN_GAP_DB),

that is, its modified z-score is below -3.5 (the textbook cut for outliers) and its mean squared
error is at least twice the median photo's (3 dB), so that a capture whose photos all fit alike
(a small MAD) flags no photo for a fraction of a dB. A flag says where to look, not why: a moving
object, a blurred or over-exposed photo or a lens unlike the others' keep a photo's error high as
well. Too few photos (under ``POSE_CHECK_MIN_VIEWS``) make no median to compare with; none is
flagged.

The training views' PSNR comes from the renders the free-space check already makes after
training (``free_space.render_training_depth``), stored in ``RUN/TRAINING_FIT_FILE``.
``stochastic-fields eval`` checks the photos it scores the same way, the training photos and the
validation photos each against their own group (a validation photo is a new view, rendered a
little worse than a training photo; a photo whose camera is wrong is rendered far worse still: on
lego's mirrored registration, the affected validation photo at 16.0 dB against 19.7-25.2 for the
other 12). The flagged photos are left out with ``prepare --exclude``, which on a scene prepared
in place maps the others again on the same features and matches.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .io_utils import atomic_write_text

#: Modified z-score below which a training photo's PSNR is an outlier (Iglewicz & Hoaglin 1993).
POSE_CHECK_Z: float = 3.5
#: ... and the least PSNR gap to the median (dB) that flags it: 3 dB is twice the median's MSE.
POSE_CHECK_MIN_GAP_DB: float = 3.0
#: Fewest training photos the check compares.
POSE_CHECK_MIN_VIEWS: int = 8
#: 1 / Phi^-1(3/4): the MAD of a normal sample times this estimates its std.
MAD_TO_STD: float = 1.4826
#: File of a run's training-view fit (``save_training_fit``).
TRAINING_FIT_FILE = "training_fit.json"
#: Flagged photos named in the printed line (the file lists all).
FLAGGED_LISTED: int = 8


@dataclass(frozen=True)
class PhotoFit:
    """The PSNR of each photo of a group (the training photos, or the validation photos) and the
    photos the check flags.

    Attributes:
        names: [T] photo names (file names where the dataset has them, else ``view_NNN``).
        psnr: [T] PSNR (dB) of each photo's render against it.
        median_db: median of ``psnr``.
        threshold_db: the PSNR under which a photo is flagged (module doc); -inf with too few photos.
        flagged: indices into ``names`` of the flagged photos, worst first.
        group: what the photos are, for people ("training", "validation").
    """

    names: tuple[str, ...]
    psnr: np.ndarray
    median_db: float
    threshold_db: float
    flagged: tuple[int, ...]
    group: str = "training"

    def summary(self) -> str:
        """One line for people: the flagged photos (the worst first) or that none is."""
        if not self.flagged:
            return (f"pose check: the {len(self.names)} {self.group} photos fit alike (median {self.median_db:.1f} dB, "
                    f"none under {self.threshold_db:.1f} dB)" if np.isfinite(self.threshold_db) else
                    f"pose check: skipped ({len(self.names)} {self.group} photos, it compares {POSE_CHECK_MIN_VIEWS} or more)")
        shown = ", ".join(f"{self.names[i]} {self.psnr[i]:.1f} dB" for i in self.flagged[:FLAGGED_LISTED])
        more = f" and {len(self.flagged) - FLAGGED_LISTED} more" if len(self.flagged) > FLAGGED_LISTED else ""
        return (f"pose check: {len(self.flagged)} of {len(self.names)} {self.group} photos fit far worse than the others "
                f"(median {self.median_db:.1f} dB): {shown}{more}. Their poses may be wrong (a mirrored "
                f"registration) or the photos unlike the others (moving objects, blur, exposure): look at "
                f"them, and prepare the capture again without those that are: prepare SCENE/images --out SCENE "
                f"--exclude NAME,... (docs/capture.md)")

    def to_dict(self) -> dict:
        return {"group": self.group, "median_psnr_db": self.median_db, "threshold_db": self.threshold_db if np.isfinite(self.threshold_db)
                else None, "flagged": [self.names[i] for i in self.flagged],
                "psnr_db": {n: float(p) for n, p in zip(self.names, self.psnr)},
                "rule": f"psnr < median - max({POSE_CHECK_Z} * {MAD_TO_STD} * MAD, {POSE_CHECK_MIN_GAP_DB} dB)"}


def check_photo_fit(names: Sequence[str], psnr: Sequence[float], group: str = "training") -> PhotoFit:
    """The check of the module doc on photos ``names`` [T] of ``group`` with PSNR ``psnr`` [T] (dB).

    ValueError when the lengths differ or a PSNR is NaN (+inf, a photo rendered exactly, is kept)."""
    psnr = np.asarray(psnr, dtype=np.float64).reshape(-1)
    names = tuple(str(n) for n in names)
    if len(names) != len(psnr):
        raise ValueError(f"pose check: {len(names)} names for {len(psnr)} PSNR values")
    if np.isnan(psnr).any():
        raise ValueError(f"pose check: PSNR of {names[int(np.flatnonzero(np.isnan(psnr))[0])]} is NaN")
    if len(psnr) == 0:
        return PhotoFit(names, psnr, float("nan"), -np.inf, (), group)
    finite = psnr[np.isfinite(psnr)]  # +inf (exact renders) left out of the median and the MAD
    median = float(np.median(finite)) if finite.size else float(np.inf)
    if len(psnr) < POSE_CHECK_MIN_VIEWS or not finite.size:
        return PhotoFit(names, psnr, median, -np.inf, (), group)
    mad = float(np.median(np.abs(finite - median)))
    threshold = median - max(POSE_CHECK_Z * MAD_TO_STD * mad, POSE_CHECK_MIN_GAP_DB)
    flagged = np.flatnonzero(psnr < threshold)
    return PhotoFit(names, psnr, median, threshold, tuple(int(i) for i in flagged[np.argsort(psnr[flagged])]), group)


def photo_names(dataset, views: Sequence[int]) -> list[str]:
    """The file name of each of ``views``' photos, or ``view_NNN`` where the dataset has none."""
    paths = getattr(dataset, "image_paths", None) or []
    return [Path(paths[v]).name if v < len(paths) else f"view_{v:03d}" for v in views]


def check_view_groups(dataset, views: Sequence[int], psnr: Sequence[float]) -> list[PhotoFit]:
    """The check on the training photos among ``views`` [N] (PSNR ``psnr`` [N], dB) and on the others
    (validation), each group against itself; a view whose PSNR is undefined (NaN) is not checked, a
    group without photos is left out."""
    train = {int(v) for v in dataset.train_indices}
    defined = [i for i in range(len(views)) if not math.isnan(float(psnr[i]))]
    fits = []
    for group, picked in (("training", [i for i in defined if int(views[i]) in train]),
                          ("validation", [i for i in defined if int(views[i]) not in train])):
        if picked:
            fits.append(check_photo_fit(photo_names(dataset, [int(views[i]) for i in picked]),
                                        [psnr[i] for i in picked], group))
    return fits


def view_groups_record(dataset, views: Sequence[int], psnr: Sequence[float]) -> dict[str, dict]:
    """``check_view_groups`` as metrics.json keeps it: {group: ``PhotoFit.to_dict``}."""
    return {fit.group: fit.to_dict() for fit in check_view_groups(dataset, views, psnr)}


def save_training_fit(run_dir: str | Path, fit: PhotoFit) -> Path:
    """Write ``fit`` to ``RUN/TRAINING_FIT_FILE`` atomically."""
    path = Path(run_dir) / TRAINING_FIT_FILE
    atomic_write_text(path, json.dumps(fit.to_dict(), indent=1))
    return path


def fit_from_dict(stored: dict) -> PhotoFit:
    """A ``PhotoFit.to_dict`` read back (training_fit.json, metrics.json's ``pose_check``), checked
    again by today's rule."""
    values = stored["psnr_db"]
    return check_photo_fit(list(values), [float(v) for v in values.values()], stored.get("group", "training"))


def load_training_fit(run_dir: str | Path) -> PhotoFit | None:
    """The run's training fit (``fit_from_dict``), or None when it has none. ValueError naming the
    file when it is malformed."""
    path = Path(run_dir) / TRAINING_FIT_FILE
    if not path.is_file():
        return None
    try:
        return fit_from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: malformed training fit ({exc})") from exc
