"""Inspect a trained run: maps, a pixel probe, a point cloud and per-view metrics (issue 6).

The logic behind ``notebooks/inspect_run.ipynb``. Everything here returns data (numpy arrays,
small dataclasses) or matplotlib ``Figure`` objects built without pyplot (no global state, no
display calls), plus a plotly figure for the interactive 3D view; the notebook only wires them
to widgets.

Conventions (docs/definitions.md §1, §3, §6):
    * Depth products are camera-z depth in scene units (``view_maps.camera_z_maps``); standard
      deviations scale the same way (``depth_std`` recalibrated by the run's calibration.json as
      eval does, the raw one as ``depth_std_raw``). ``depth_std`` is the total std (epistemic + termination
      spread, law of total variance).
    * Colour products are in colour units [0, 1]; ``colour_std`` is the per-channel std over the
      K rendered trajectories.
    * Depth maps are meaningful where a surface was hit: figures grey out pixels with opacity
      <= ``view_maps.OPACITY_MASK`` (those rays report ``depth = far`` per draw), and depth scores
      use the same mask with valid ground truth.
    * Pixel ``(u, v)`` is column ``u`` and row ``v`` (integer indices; the ray goes through the
      pixel centre ``(u + 0.5, v + 0.5)``).
    * Point clouds are ``products.pointcloud.CloudArrays`` (per-point ``depth_std``, ``opacity``
      and ``confidence = exp(-(depth_std / depth) / 0.05)``, see that module).

Rendering: every view goes through the model's own ``render_view`` with the run's render
options (empty-space skipping included), so the maps are the ones ``eval`` scores; only K, the
quadrature and the colour estimator are chosen here, per call (a fixed K: no adaptive K). Noise:
the view is rendered in chunks of ``chunk_rays`` rays, each chunk with its own generator seeded
from ``(seed, view, chunk)``. The maps of one (view, K, quadrature) are therefore one fixed
Monte-Carlo estimate, and ``probe_pixel`` re-renders the pixel's chunk (``SNeRF.render_chunk``)
with the same generator, so its K depth draws are exactly the ones behind the maps. The probe
shows every sample of the ray (the field evaluated at all of them); the draws' weights are 0 at
the samples the occupancy grid skipped. The pixel probe needs a stochastic field and is S-NeRF only;
baselines render with their own K where they fix it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
import torch
from matplotlib.figure import Figure
import matplotlib

from .cameras import generate_rays_for_view, image_size, intrinsics_3x3
from .distributions import RectifiedNormal
from . import metrics as M
from .plots import calibration_figure, interval_reliability_figure
from .calibration import apply_calibration, load_run_calibration
from .evaluation import ColourTerms, calibrated_depth_scores, depth_samples, score_colour, score_depth
from .view_maps import OPACITY_MASK, camera_z_maps
from .models.snerf import SNeRF
from .products.depth_maps import DepthProducts, compute_depth_products
from .products.pointcloud import UNCERTAINTY_CMAP, CloudArrays, cloud_from_products, uncertainty_range
from .rays import PackedRaySamples, RayBundle
from .renderer import RenderOptions, check_colour_estimator, seeded_chunks
from .samplers import sample_along_rays
from .trainer import load_trained_model

Quadrature = Literal["alpha", "trapezoid"]

#: Environment variable the notebook reads its run folder from (tests point it at a tiny run).
RUN_ENV_VAR = "STOCHASTIC_FIELDS_RUN"

#: Units written on colour bars and axes.
DEPTH_UNITS = "scene units"
COLOUR_UNITS = "colour units [0, 1]"


@dataclass(frozen=True)
class MapSpec:
    """How one map is shown: label, colour-bar unit, colour map, and whether it is a depth
    quantity (masked by opacity), needs ground truth, needs a depth map fitted with the
    free-space check (``calibrate --free-space``), the occlusion-edge term (``--edge-term``) or the
    parallax term (``--parallax-term``)."""

    label: str
    unit: str
    cmap: str
    depth: bool = False
    needs_gt_depth: bool = False
    needs_free_space: bool = False
    needs_edge_term: bool = False
    needs_parallax_term: bool = False


#: Every map ``RunInspector.render`` returns that can be shown, in the notebook's order.
MAP_SPECS: dict[str, MapSpec] = {
    "colour_mean": MapSpec("colour mean", f"RGB, {COLOUR_UNITS}", ""),
    "colour_std": MapSpec("colour std (mean over RGB)", COLOUR_UNITS, "magma"),
    "depth_mean": MapSpec("depth mean (camera z)", DEPTH_UNITS, "turbo", depth=True),
    "depth_std_epistemic": MapSpec("depth std, epistemic (over K draws)", DEPTH_UNITS, "magma", depth=True),
    "depth_std_spread": MapSpec("depth std, termination spread", DEPTH_UNITS, "magma", depth=True),
    "depth_std": MapSpec("depth std, total", DEPTH_UNITS, "magma", depth=True),
    "depth_free_space": MapSpec("free-space violation (in front of a training view's surface)", DEPTH_UNITS,
                                "magma", depth=True, needs_free_space=True),
    "depth_edge": MapSpec("occlusion-edge size (depth range within 2 pixels)", DEPTH_UNITS, "magma", depth=True,
                          needs_edge_term=True),
    "depth_parallax": MapSpec("parallax angle (widest between training views that see the point)", "degrees",
                              "viridis", depth=True, needs_parallax_term=True),
    "opacity": MapSpec("opacity (accumulated)", "[0, 1]", "gray"),
    "colour_abs_error": MapSpec("|colour mean - GT| (mean over RGB)", COLOUR_UNITS, "inferno"),
    "depth_abs_error": MapSpec("|depth mean - GT depth|", DEPTH_UNITS, "inferno", depth=True, needs_gt_depth=True),
}


@dataclass(frozen=True)
class ViewInfo:
    """One view of the run's dataset: its index, split ('train'/'test') and image file name."""

    index: int
    split: str
    name: str

    @property
    def label(self) -> str:
        return f"{self.split} {self.index:03d} ({self.name})"


class RunInspector:
    """A trained run loaded once, with cached renders per (view, K, quadrature).

    Args:
        run_dir: a run folder (``config.json`` + ``checkpoint.pt``).
        device: 'cpu', 'cuda' or None (the run's own setting, 'auto' = CUDA when present).
        seed: base seed of the rendering noise (see the module docstring).
    """

    def __init__(self, run_dir: str | Path, device: str | None = None, seed: int = 0):
        self.run_dir = Path(run_dir)
        if not self.run_dir.is_dir():
            raise FileNotFoundError(f"run folder {self.run_dir} does not exist (train a run first, e.g. `make demo`)")
        self.cfg, self.model, self.dataset = load_trained_model(self.run_dir, device=device)
        self.calibration = load_run_calibration(self.run_dir)  # the run's depth recalibration, as eval applies it
        self.device = next(self.model.parameters()).device
        self.seed = int(seed)
        self._colour_estimator = self.model.default_render_options().colour_estimator
        self.height, self.width = image_size(self.dataset.cameras)
        self._cache: dict[tuple[int, int, str], dict[str, np.ndarray]] = {}
        self._depth_cache: dict[tuple[int, int, str], DepthProducts] = {}
        self._metrics_cache: dict[tuple[int, int, str], dict[str, Any]] = {}

    # ------------------------------------------------------------------ basics
    @property
    def is_stochastic_field(self) -> bool:
        """True for S-NeRF runs (the pixel probe needs ``model.field``)."""
        return isinstance(self.model, SNeRF)

    @property
    def default_num_draws(self) -> int:
        return int(self.model.default_render_options().num_draws)

    @property
    def default_quadrature(self) -> str:
        return str(self.model.render_settings.quadrature)

    @property
    def colour_estimator(self) -> str:
        """Colour statistics of the renders: 'draws' (docs/definitions.md §3) or 'rao_blackwell' (density draws only,
        colour noise integrated exactly; see ``RenderSettings.colour_estimator``)."""
        return self._colour_estimator

    @colour_estimator.setter
    def colour_estimator(self, value: str) -> None:
        if check_colour_estimator(value) != self.colour_estimator:  # the cached renders were made with the other one
            self._colour_estimator = value
            self.clear_cache()

    def views(self) -> list[ViewInfo]:
        """Every view with its split, test views first (the held-out ones are the interesting ones)."""
        names = [Path(p).name for p in self.dataset.image_paths]
        if len(names) != self.dataset.num_views:
            names = [f"view_{i:03d}" for i in range(self.dataset.num_views)]
        test = [ViewInfo(i, "test", names[i]) for i in self.dataset.test_indices]
        train = [ViewInfo(i, "train", names[i]) for i in self.dataset.train_indices]
        return test + train

    def summary(self) -> str:
        """A few printable lines: run, method, scene, views, image size, rendering defaults."""
        ds, rs = self.dataset, self.model.render_settings
        depth = "yes" if getattr(ds, "depths", None) is not None else "no"
        return "\n".join([
            f"run:        {self.run_dir}",
            f"method:     {self.cfg.method} ({self.cfg.field.backend} field), {self.cfg.train.iterations} iterations"
            + (f" or {self.cfg.train.minutes:g} minutes" if self.cfg.train.minutes > 0 else ""),
            f"scene:      {ds.name} ({ds.root})",
            f"views:      {len(ds.train_indices)} train, {len(ds.test_indices)} test, {self.width}x{self.height} px, "
            f"ground-truth depth: {depth}",
            f"rendering:  K={rs.num_draws} draws, S={rs.num_samples} samples/ray, quadrature={rs.quadrature}, "
            f"spacing={rs.spacing}, colour estimator={self.colour_estimator}",
            f"device:     {self.device}",
        ])

    def _check_view(self, view: int) -> int:
        if not isinstance(view, (int, np.integer)) or not 0 <= int(view) < self.dataset.num_views:
            raise IndexError(f"view {view!r} out of range: the run has {self.dataset.num_views} views")
        return int(view)

    def _args(self, num_draws: int | None, quadrature: str | None) -> tuple[int, str]:
        K = self.default_num_draws if num_draws is None else int(num_draws)
        q = self.default_quadrature if quadrature is None else str(quadrature)
        if K < 1:
            raise ValueError(f"num_draws must be >= 1, got {num_draws!r}")
        if q not in ("alpha", "trapezoid"):
            raise ValueError(f"quadrature must be 'alpha' or 'trapezoid', got {quadrature!r}")
        return K, q

    def _options(self, num_draws: int, quadrature: str) -> RenderOptions:
        """The render options of (K, quadrature) with this inspector's colour estimator, draws kept."""
        return self.model.render_options(num_draws=num_draws, quadrature=quadrature,
                                         colour_estimator=self._colour_estimator, keep_draws=True)

    def _rays(self, view: int) -> RayBundle:
        """[H, W] rays of ``view`` on the model's device."""
        ds = self.dataset
        return generate_rays_for_view(ds.cameras, view, ds.near, ds.far).to(self.device)

    def _generator(self, view: int, chunk: int) -> torch.Generator:
        return seeded_chunks(self.seed, view, self.device)(chunk)

    def ground_truth(self, view: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(colour [H, W, 3] in [0, 1], camera-z depth [H, W] with 0 where no surface, or None)."""
        view = self._check_view(view)
        gt = self.dataset.images[view].cpu().numpy().astype(np.float32)
        depths = getattr(self.dataset, "depths", None)
        return gt, (None if depths is None else depths[view].cpu().numpy().astype(np.float32))

    # ------------------------------------------------------------------ rendering
    @torch.no_grad()
    def _render_maps(self, view: int, num_draws: int, quadrature: str) -> dict[str, torch.Tensor]:
        """Renderer maps of ``view`` (ray distance, ``RadianceModel.render_view``), chunk-seeded."""
        return self.model.render_view(self._rays(view), self._options(num_draws, quadrature),
                                      generator=seeded_chunks(self.seed, view, self.device))

    def render(self, view: int, num_draws: int | None = None, quadrature: Quadrature | None = None
               ) -> dict[str, np.ndarray]:
        """Camera-z products of one view, cached per (view, K, quadrature).

        Returns (numpy float32):
            colour_mean, colour_std [H, W, 3]; depth_mean, depth_std (total), depth_std_epistemic,
            depth_std_spread, opacity [H, W]; depth_draws [H, W, K]; colour_abs_error [H, W]
            (|mean - GT| averaged over RGB); depth_abs_error [H, W] when the scene has
            ground-truth depth (NaN where it has none). The returned dict is the cached object:
            do not modify it.
        """
        view = self._check_view(view)
        K, q = self._args(num_draws, quadrature)
        key = (view, K, q)
        if key not in self._cache:
            raw = self._render_maps(view, K, q)
            ds = self.dataset
            camera = (intrinsics_3x3(ds.cameras)[view].double().cpu().numpy(),
                      ds.cameras.extrinsics[view].double().cpu().numpy())
            self._depth_cache[key] = compute_depth_products(
                raw, *camera, near=float(ds.near[view]),
                far=float(ds.far[view]), min_opacity=OPACITY_MASK, calibration=self.calibration)
            products = apply_calibration(camera_z_maps(raw), self.calibration, camera=camera)
            gt, gt_depth = self.ground_truth(view)
            products["colour_abs_error"] = np.abs(products["colour_mean"] - gt).mean(axis=-1).astype(np.float32)
            if gt_depth is not None:
                err = np.abs(products["depth_mean"] - gt_depth)
                products["depth_abs_error"] = np.where(gt_depth > 0, err, np.nan).astype(np.float32)
            self._cache[key] = products
        return self._cache[key]

    def depth_products(self, view: int, num_draws: int | None = None, quadrature: Quadrature | None = None
                       ) -> DepthProducts:
        """``products.depth_maps.DepthProducts`` of the same render (quantiles 5%/95%, ``valid`` =
        opacity >= OPACITY_MASK, camera pose), cached with it."""
        self.render(view, num_draws, quadrature)
        return self._depth_cache[(int(view), *self._args(num_draws, quadrature))]

    def cached_keys(self) -> list[tuple[int, int, str]]:
        """The (view, K, quadrature) renders held in memory."""
        return list(self._cache)

    def clear_cache(self) -> None:
        self._cache.clear()
        self._depth_cache.clear()
        self._metrics_cache.clear()

    def map_names(self) -> list[str]:
        """Names of the maps this run can show (error against GT depth only where it exists, the
        free-space violation only where the run's depth map checks it, the edge size and the parallax
        angle only where it has their terms)."""
        has_depth = getattr(self.dataset, "depths", None) is not None
        cal = self.calibration
        checks = cal is not None and cal.depth is not None and cal.depth.free_space
        edges = cal is not None and cal.depth is not None and cal.depth.edge_weight > 0.0
        parallax = cal is not None and cal.depth is not None and cal.depth.parallax_weight > 0.0
        return [n for n, s in MAP_SPECS.items()
                if (has_depth or not s.needs_gt_depth) and (checks or not s.needs_free_space)
                and (edges or not s.needs_edge_term) and (parallax or not s.needs_parallax_term)]

    # ------------------------------------------------------------------ figures of maps
    def map_figure(self, view: int, name: str, num_draws: int | None = None, quadrature: Quadrature | None = None,
                   *, mask_empty: bool = True, figsize: tuple[float, float] = (6.0, 4.2)) -> Figure:
        """One map with a colour bar in its units. Depth quantities grey out pixels with opacity
        <= OPACITY_MASK when ``mask_empty`` (rays that hit nothing report depth = far)."""
        if name not in MAP_SPECS:
            raise KeyError(f"unknown map {name!r}; choose from {list(MAP_SPECS)}")
        products = self.render(view, num_draws, quadrature)
        if name not in products:
            spec = MAP_SPECS[name]
            need = ("a depth map fitted with the free-space check (stochastic-fields calibrate --run RUN --free-space)"
                    if spec.needs_free_space else
                    "a depth map fitted with the occlusion-edge term (stochastic-fields calibrate --run RUN --edge-term)"
                    if spec.needs_edge_term else
                    "a depth map fitted with the parallax term (stochastic-fields calibrate --run RUN --parallax-term)"
                    if spec.needs_parallax_term else "ground-truth depth")
            raise KeyError(f"map {name!r} needs {need}, which run {self.run_dir} has not")
        K, q = self._args(num_draws, quadrature)
        fig = Figure(figsize=figsize)
        ax = fig.add_subplot(1, 1, 1)
        _draw_map(fig, ax, products, name, mask_empty=mask_empty)
        ax.set_title(f"{MAP_SPECS[name].label}\nview {view}, K={K}, {q}", fontsize=10)
        fig.tight_layout()
        return fig

    def overview_figure(self, view: int, num_draws: int | None = None, quadrature: Quadrature | None = None,
                        names: Sequence[str] | None = None, *, ncols: int = 4) -> Figure:
        """Ground truth and every map of one view on a grid, each with its colour bar."""
        products = self.render(view, num_draws, quadrature)
        K, q = self._args(num_draws, quadrature)
        gt, _ = self.ground_truth(view)
        names = [n for n in (names or self.map_names()) if n in products]
        panels = ["gt_colour", *names]
        nrows = -(-len(panels) // ncols)
        fig = Figure(figsize=(3.6 * ncols, 2.9 * nrows))
        for i, name in enumerate(panels):
            ax = fig.add_subplot(nrows, ncols, i + 1)
            if name == "gt_colour":
                ax.imshow(np.clip(gt, 0, 1))
                ax.set_title("ground truth colour", fontsize=9)
                ax.set_axis_off()
                continue
            _draw_map(fig, ax, products, name, mask_empty=True)
            ax.set_title(MAP_SPECS[name].label, fontsize=9)
        fig.suptitle(f"view {view}: K={K} draws, {q} quadrature (grey: opacity <= {OPACITY_MASK})", fontsize=11)
        fig.tight_layout()
        return fig

    # ------------------------------------------------------------------ pixel probe
    @torch.no_grad()
    def probe_pixel(self, view: int, u: int, v: int, num_draws: int | None = None,
                    quadrature: Quadrature | None = None) -> dict[str, Any]:
        """Everything along the ray of pixel (column ``u``, row ``v``), from the same draws as
        ``render(view, K, quadrature)``.

        Returns (numpy float32 arrays unless stated):
            depth_draws [K]: camera-z depth D_k of each trajectory (equal to
                ``render(...)["depth_draws"][v, u]``).
            t [S]: ray distance of the sample midpoints; z [S]: their camera-z depth.
            density_mean [S]: E[relu(Y)], Y ~ N(mu_a, s_a^2) (``RectifiedNormal.mean``),
                per unit ray distance; density_std [S]: its standard deviation.
            weights [K, S]: quadrature weights w_ik of each trajectory (0 at samples the
                occupancy grid skipped as empty space).
            colour_draws [K, 3]; depth_mean, depth_std (total, camera z), opacity: floats.
            gt_depth: float or None (None also where the scene has no surface at the pixel);
            gt_colour [3]; view, u, v: ints.
        """
        view = self._check_view(view)
        if not self.is_stochastic_field:
            raise NotImplementedError(
                f"the pixel probe needs a stochastic field (S-NeRF); run {self.run_dir} is method {self.cfg.method!r}")
        if not (0 <= int(u) < self.width and 0 <= int(v) < self.height):
            raise IndexError(f"pixel (u={u}, v={v}) outside the {self.width}x{self.height} image")
        u, v = int(u), int(v)
        K, q = self._args(num_draws, quadrature)
        rays = self._rays(view)
        options = self._options(K, q)
        chunk, i = divmod(v * self.width + u, options.chunk_rays)
        start = chunk * options.chunk_rays
        flat_chunk = rays.flatten()[start:start + options.chunk_rays]
        out = self.model.render_chunk(flat_chunk, options, generator=self._generator(view, chunk))
        z = rays.z_scale[v, u].double()
        if isinstance(out.samples, PackedRaySamples):
            params, t, weights = self._dense_ray(out, flat_chunk[i:i + 1], i, options)
        else:
            params = out.params.map(lambda t: t[i])  # [S]
            t, weights = out.samples.t_mids[i], out.extras["weights"][i]
        dist = RectifiedNormal(params.density_loc, params.density_scale)
        stats = out.stats
        depth_var = stats.depth_var_total[i].double().clamp_min(0)
        gt, gt_depth = self.ground_truth(view)
        f32 = lambda x: x.detach().cpu().numpy().astype(np.float32)  # noqa: E731
        return {
            "view": view, "u": u, "v": v, "num_draws": K, "quadrature": q,
            "depth_draws": f32(stats.depth_draws[i].double() * z),
            "t": f32(t),
            "z": f32(t.double() * z),
            "density_mean": f32(dist.mean),
            "density_std": f32(dist.stddev),
            "weights": f32(weights),
            "colour_draws": f32(stats.colour_draws[i]),
            "depth_mean": float(stats.depth_mean[i].double() * z),
            "depth_std": float(depth_var.sqrt() * z),
            "opacity": float(stats.opacity[i]),
            "gt_colour": gt[v, u],
            "gt_depth": None if gt_depth is None or not gt_depth[v, u] > 0 else float(gt_depth[v, u]),
        }

    @torch.no_grad()
    def _dense_ray(self, out, ray: RayBundle, i: int, options: RenderOptions):
        """Every sample of ray ``i`` of a chunk rendered with skipped empty space: its field
        parameters [S] and midpoints [S], and the weights [K, S] of ``out``'s draws (zero at the
        samples the occupancy grid skipped, which were not evaluated)."""
        settings = options.settings_for(self.model.render_settings)
        dense = sample_along_rays(ray, settings.num_samples, spacing=settings.spacing)
        params = self.model.field(dense.positions, dense.directions).map(lambda t: t[0])
        keep = self.model.occupied(dense.positions)[0]
        mine = out.samples.ray_indices == i
        if int(keep.sum()) != int(mine.sum()):
            raise RuntimeError(f"pixel's ray: {int(mine.sum())} rendered samples but {int(keep.sum())} occupied")
        packed = out.extras["weights"][:, mine]
        weights = packed.new_zeros(packed.shape[0], settings.num_samples)
        weights[:, keep] = packed
        return params, dense.t_mids[0], weights

    def probe_figure(self, view: int, u: int, v: int, num_draws: int | None = None,
                     quadrature: Quadrature | None = None, *, bins: int | None = None) -> Figure:
        """Three panels: where the pixel is, a histogram of its K depth draws (with the mean, the
        total std and the ground-truth depth), and density mean +- std along its ray with the
        mean weight E_k[w_ik]."""
        probe = self.probe_pixel(view, u, v, num_draws, quadrature)
        products = self.render(view, probe["num_draws"], probe["quadrature"])
        return probe_figure(probe, products["colour_mean"], bins=bins)

    # ------------------------------------------------------------------ point cloud
    def point_cloud(self, views: int | Sequence[int], num_draws: int | None = None,
                    quadrature: Quadrature | None = None, min_confidence: float = 0.0,
                    min_opacity: float = OPACITY_MASK) -> CloudArrays:
        """World points of the depth means of ``views`` (``products.pointcloud.cloud_from_products``:
        back-projection, normals, per-point depth_std / opacity / confidence), keeping pixels with
        opacity >= ``min_opacity`` and points with confidence >= ``min_confidence``."""
        views = [views] if isinstance(views, (int, np.integer)) else list(views)
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
        if not 0.0 <= min_opacity <= 1.0:
            raise ValueError(f"min_opacity must be in [0, 1], got {min_opacity}")
        clouds = []
        for view in views:
            dp = self.depth_products(view, num_draws, quadrature)
            cloud = cloud_from_products(dp, view=int(view), mask=dp.opacity >= min_opacity)
            clouds.append(cloud.select(cloud.attributes["confidence"] >= min_confidence))
        return CloudArrays.concatenate(clouds)

    # ------------------------------------------------------------------ metrics
    def view_metrics(self, view: int, num_draws: int | None = None, quadrature: Quadrature | None = None
                     ) -> dict[str, Any]:
        """Sparsification and calibration curves of one view, and its scores, cached with its render
        (the figures below and the notebook ask for them several times; do not modify the result).

        Returns:
            scores: ``evaluation.score_view``'s (PSNR, SSIM, NLL, correlations, AUSE, depth scores).
            colour_sparsification: RMSE curve (``metrics.colour_sparsification``).
            colour_calibration: pooled over pixels and channels (``metrics.calibration_curve``).
            depth_sparsification, depth_calibration, depth_intervals: on pixels with ground-truth
                depth and opacity > OPACITY_MASK (``evaluation.calibrated_depth_scores``, recalibrated
                intervals as eval scores them; the intervals' coverage, width, interval scores and
                CRPS: ``metrics.interval_sharpness``), or None (no ground truth, fewer than 2 such
                pixels, or for the sparsification a constant depth std).
            depth_mask [H, W] bool or None.
        """
        key = (self._check_view(view), *self._args(num_draws, quadrature))
        if key not in self._metrics_cache:
            self._metrics_cache[key] = self._view_metrics(*key)
        return self._metrics_cache[key]

    def _view_metrics(self, view: int, num_draws: int, quadrature: str) -> dict[str, Any]:
        """``view_metrics``, computed."""
        products = self.render(view, num_draws, quadrature)
        gt, gt_depth = self.ground_truth(view)
        colour = ColourTerms.of(products, gt)
        out: dict[str, Any] = {
            "scores": score_colour(products, gt, colour),
            "colour_sparsification": M.colour_sparsification(gt, products["colour_mean"],
                                                             products["colour_std"].astype(np.float64) ** 2, "rmse"),
            "colour_calibration": colour.calibration,
            "depth_sparsification": None, "depth_calibration": None, "depth_intervals": None, "depth_mask": None,
        }
        samples = depth_samples(products, gt_depth)
        if samples is not None:
            depth = calibrated_depth_scores(samples, self.calibration)
            out["scores"].update(score_depth(samples, self.calibration, depth))
            if samples.gt.size >= 2:
                out["depth_mask"] = (gt_depth > 0) & (products["opacity"] > OPACITY_MASK)  # depth_samples' pixels
                out["depth_sparsification"] = depth["sparsification"]
                out["depth_calibration"] = depth["calibration"]
                out["depth_intervals"] = depth["intervals"]
        return out

    def sparsification_figure(self, view: int, num_draws: int | None = None,
                              quadrature: Quadrature | None = None) -> Figure:
        """Colour (and depth, where ground truth exists) sparsification curves of one view."""
        m = self.view_metrics(view, num_draws, quadrature)
        curves = {"colour (RMSE)": m["colour_sparsification"]}
        if m["depth_sparsification"] is not None:
            curves["depth (RMSE, scene units)"] = m["depth_sparsification"]
        return sparsification_figure(curves, title=f"view {view}: sparsification")

    def calibration_figure(self, view: int, num_draws: int | None = None,
                           quadrature: Quadrature | None = None) -> Figure:
        """Colour (and depth) calibration curves of one view."""
        m = self.view_metrics(view, num_draws, quadrature)
        curves = {"colour": m["colour_calibration"]}
        if m["depth_calibration"] is not None:
            curves["depth"] = m["depth_calibration"]
        return calibration_figure(curves, title=f"view {view}: calibration")

    def interval_figure(self, view: int, num_draws: int | None = None,
                        quadrature: Quadrature | None = None) -> Figure | None:
        """The depth intervals' reliability diagram (with the narrowest and widest third of the
        bands) beside their sharpness histogram, as eval draws them for a whole run
        (``plots.interval_reliability_figure``); None when the view has no scored depth."""
        m = self.view_metrics(view, num_draws, quadrature)
        if m["depth_intervals"] is None:
            return None
        return interval_reliability_figure({"depth": m["depth_intervals"]},
                                           title=f"view {view}: depth intervals ({m['depth_intervals']['num_values']} values)")


# ---------------------------------------------------------------------------- drawing helpers
def _draw_map(fig: Figure, ax, products: dict[str, np.ndarray], name: str, *, mask_empty: bool) -> None:
    """Draw map ``name`` on ``ax`` with a colour bar labelled with its unit."""
    spec = MAP_SPECS[name]
    ax.set_xticks([])
    ax.set_yticks([])
    if name == "colour_mean":
        ax.imshow(np.clip(products[name], 0.0, 1.0))
        ax.set_xlabel(spec.unit, fontsize=8)
        return
    values = products[name].astype(np.float64)
    if values.ndim == 3:
        values = values.mean(axis=-1)
    if mask_empty and spec.depth:
        values = np.where(products["opacity"] > OPACITY_MASK, values, np.nan)
    finite = values[np.isfinite(values)]
    vmin, vmax = (0.0, 1.0) if name == "opacity" else (None, None)
    if finite.size and name != "opacity":
        vmin = 0.0 if name != "depth_mean" else float(np.percentile(finite, 1))
        vmax = float(np.percentile(finite, 99))
        if vmax <= vmin:
            vmax = vmin + max(abs(vmin), 1.0) * 1e-3
    cmap = matplotlib.colormaps[spec.cmap].with_extremes(bad="0.75")
    im = ax.imshow(values, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    bar.set_label(spec.unit, fontsize=8)
    bar.ax.tick_params(labelsize=7)


def probe_figure(probe: dict[str, Any], colour_mean: np.ndarray, *, bins: int | None = None) -> Figure:
    """Figure of a ``RunInspector.probe_pixel`` result; ``colour_mean`` [H, W, 3] locates the pixel."""
    fig = Figure(figsize=(13.0, 3.8))
    ax_img, ax_hist, ax_ray = (fig.add_subplot(1, 3, i) for i in (1, 2, 3))
    u, v = probe["u"], probe["v"]
    ax_img.imshow(np.clip(colour_mean, 0, 1))
    ax_img.plot([u], [v], marker="+", color="red", markersize=16, markeredgewidth=2)
    ax_img.set_title(f"view {probe['view']}, pixel (u={u}, v={v})", fontsize=10)
    ax_img.set_xticks([])
    ax_img.set_yticks([])

    draws = probe["depth_draws"]
    K = draws.size
    nbins = bins or int(np.clip(np.sqrt(K) * 2, 5, 40))
    ax_hist.hist(draws, bins=nbins, color="C0", alpha=0.8, label=f"{K} draws D_k")
    ax_hist.axvline(probe["depth_mean"], color="k", label=f"mean {probe['depth_mean']:.3g}")
    ax_hist.axvspan(probe["depth_mean"] - probe["depth_std"], probe["depth_mean"] + probe["depth_std"], color="k",
                    alpha=0.1, label=f"+- total std {probe['depth_std']:.3g}")
    if probe["gt_depth"] is not None:
        ax_hist.axvline(probe["gt_depth"], color="C3", linestyle="--", label=f"GT {probe['gt_depth']:.3g}")
    ax_hist.set_xlabel(f"depth, camera z ({DEPTH_UNITS})")
    ax_hist.set_ylabel("draws")
    ax_hist.set_title(f"K={K} depth draws ({probe['quadrature']}), opacity {probe['opacity']:.2f}", fontsize=10)
    ax_hist.legend(fontsize=7)

    z, mean, std = probe["z"], probe["density_mean"], probe["density_std"]
    ax_ray.fill_between(z, np.maximum(mean - std, 0.0), mean + std, color="C1", alpha=0.25, label="mean +- std")
    ax_ray.plot(z, mean, color="C1", label="E[density]")
    ax_ray.set_xlabel(f"sample depth, camera z ({DEPTH_UNITS})")
    ax_ray.set_ylabel("density (per unit ray distance)")
    w = ax_ray.twinx()
    w.plot(z, probe["weights"].mean(axis=0), color="C2", linestyle=":", label="E_k[w]")
    w.set_ylabel("mean weight E_k[w]", color="C2", fontsize=8)
    w.tick_params(labelsize=7)
    if probe["gt_depth"] is not None:
        ax_ray.axvline(probe["gt_depth"], color="C3", linestyle="--", label="GT depth")
    lines = ax_ray.get_legend_handles_labels()
    lines_w = w.get_legend_handles_labels()
    ax_ray.legend(lines[0] + lines_w[0], lines[1] + lines_w[1], fontsize=7, loc="upper right")
    ax_ray.set_title("density along the ray", fontsize=10)
    fig.tight_layout()
    return fig


def sparsification_figure(curves: dict[str, M.SparsificationResult], title: str = "sparsification") -> Figure:
    """One panel per curve: normalised model curve (solid) and oracle (dashed), the layout of
    ``plots.plot_sparsification`` (which writes files; this returns the Figure)."""
    fig = Figure(figsize=(5.2 * len(curves), 4.0))
    for i, (name, r) in enumerate(curves.items()):
        ax = fig.add_subplot(1, len(curves), i + 1)
        ax.plot(r.fractions, r.model_normalised, color="C0", label=f"by uncertainty (AUSE {r.ause_normalised:.3g})")
        ax.plot(r.fractions, r.oracle_normalised, color="C0", linestyle="--", label="oracle (by true error)")
        ax.set_xlabel("fraction of pixels removed (most uncertain first)")
        ax.set_ylabel(f"{r.metric.upper()} of kept / {r.metric.upper()} of all")
        ax.set_title(f"{name}, {r.num_pixels} px", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig


def format_scores(scores: dict[str, Any]) -> str:
    """Printable lines of ``evaluation.score_view`` scores (correlations show NaN and why when
    undefined)."""
    lines = []
    for name, value in scores.items():
        if isinstance(value, M.CorrelationResult):
            text = f"{value.value:.4g}" + ("" if value.defined else f"  (undefined: {value.reason})")
        else:
            text = f"{float(value):.4g}"
        lines.append(f"  {name:<24s} {text}")
    return "\n".join(lines)


def _select(values: np.ndarray, threshold: float | None, max_points: int) -> np.ndarray:
    """Indices of points with ``values <= threshold`` (all if None), evenly thinned to ``max_points``."""
    keep = np.flatnonzero(np.ones(values.shape, bool) if threshold is None else values <= threshold)
    if keep.size > max_points:
        keep = keep[np.linspace(0, keep.size - 1, max_points).round().astype(np.int64)]
    return keep


def plotly_cloud_figure(points: np.ndarray, colours: np.ndarray, values: np.ndarray, threshold: float | None = None,
                        *, colour_by: Literal["uncertainty", "rgb"] = "uncertainty", max_points: int = 30000,
                        value_label: str = f"depth std ({DEPTH_UNITS})", point_size: float = 2.0):
    """Interactive 3D scatter (plotly) of the points whose uncertainty ``values`` <= ``threshold``.

    Shapes: points [N, 3], colours [N, 3] in [0, 1], values [N]. Colour by uncertainty (the
    exported clouds' colour map and range, with a colour bar) or by the points' RGB colours; at
    most ``max_points`` points (evenly thinned). Needs plotly.
    """
    import plotly.graph_objects as go  # heavy optional dependency (plotly): loaded only when used

    idx = _select(values, threshold, max_points)
    p, c, val = points[idx], colours[idx], values[idx]
    if colour_by == "uncertainty":
        lo, hi = uncertainty_range(values)  # 0 to the 99th percentile, as the exported clouds
        marker = dict(size=point_size, color=val, colorscale=UNCERTAINTY_CMAP, colorbar=dict(title=value_label),
                      cmin=lo, cmax=hi)
    elif colour_by == "rgb":
        rgb = (np.clip(c, 0, 1) * 255).round().astype(int)
        marker = dict(size=point_size, color=[f"rgb({r},{g},{b})" for r, g, b in rgb])
    else:
        raise ValueError(f"colour_by must be 'uncertainty' or 'rgb', got {colour_by!r}")
    # numpy arrays travel as binary typed arrays; per-point strings (hover texts) would not
    fig = go.Figure(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers", marker=marker, customdata=val,
                                 hovertemplate=f"{value_label}: %{{customdata:.3g}}<extra></extra>"))
    shown = "all" if threshold is None else f"{value_label} <= {threshold:.3g}"
    fig.update_layout(title=f"{idx.size} of {len(values)} points ({shown})", height=520,
                      margin=dict(l=0, r=0, t=40, b=0), scene=dict(aspectmode="data"))
    return fig


def static_cloud_figure(points: np.ndarray, colours: np.ndarray, values: np.ndarray, threshold: float | None = None,
                        *, max_points: int = 20000, value_label: str = f"depth std ({DEPTH_UNITS})",
                        elev: float = 50.0, azim: float = -100.0) -> Figure:
    """Static fallback of ``plotly_cloud_figure``: matplotlib 3D scatters coloured by RGB and by
    uncertainty, of the points with ``values <= threshold``."""
    idx = _select(values, threshold, max_points)
    p, c, val = points[idx], np.clip(colours[idx], 0, 1), values[idx]
    fig = Figure(figsize=(11.0, 4.8))
    shown = "all" if threshold is None else f"{value_label} <= {threshold:.3g}"
    lo, hi = uncertainty_range(values)
    for i, (title, colour) in enumerate((("colour mean", c), ("uncertainty", val))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        sc = ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=colour, s=1.0, cmap=UNCERTAINTY_CMAP if i else None,
                        vmin=lo if i else None, vmax=hi if i else None, depthshade=False)
        ax.view_init(elev=elev, azim=azim)
        extent = np.ptp(p, axis=0) if len(p) else np.zeros(3)
        if extent.max() > 0:  # equal scale on the three axes (a flat axis gets 1% of the largest)
            ax.set_box_aspect(tuple(np.maximum(extent, extent.max() / 100)))
        ax.set_title(f"{title}: {idx.size} of {len(values)} points\n({shown})", fontsize=9)
        ax.tick_params(labelsize=6)
        if i:
            bar = fig.colorbar(sc, ax=ax, fraction=0.04, pad=0.08)
            bar.set_label(value_label, fontsize=8)
    fig.tight_layout()
    return fig


__all__ = [
    "COLOUR_UNITS", "DEPTH_UNITS", "MAP_SPECS", "MapSpec", "RUN_ENV_VAR", "RunInspector", "ViewInfo",
    "calibration_figure", "format_scores", "plotly_cloud_figure", "probe_figure", "sparsification_figure",
    "static_cloud_figure",
]
