"""The render and loss settings of an experiment: plain dataclasses with their declared ranges.

They live apart from the renderer and the losses so that building the configuration and the
command line needs neither torch nor any module that imports it (``--help`` stays fast);
``renderer`` and ``losses`` use them from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from .constants import COLOUR_MIN_TRANSMITTANCE, OCCUPANCY_ALPHA_THRESHOLD, OCCUPANCY_UPPER_NUM_STD
from .validation import Checker, boolean, check_fields, choice, colour_or_none, integer, real

Spacing = Literal["linear", "disparity"]


@dataclass
class LossConfig:
    """Weights and choices of the variational loss."""

    likelihood_std: float = 0.05
    """sigma_n: standard deviation of the Gaussian pixel likelihood (colour units, [0, 1]); the starting value when learned. Range: a finite number > 0."""
    learn_likelihood_std: bool = True
    """Learn sigma_n (one per colour channel) with the rest of the objective instead of fixing it (default: learned; the paper fixes it). Render with render.colour_variance='predictive' to add sigma_n^2 to the colour variance."""
    likelihood_estimator: Literal["draws", "rao_blackwell"] = "draws"
    """How the expected pixel log-likelihood E_q[log N(c | C_k, v_k)] is estimated over the K training trajectories: 'draws' draws each sample's colour (the paper); 'rao_blackwell' draws the density only and takes the colour's expectation exactly, E[(C_k - c)^2 | w_k] = (sum_i w_ik E[r_i] - c)^2 + sum_i w_ik^2 Var[r_i] (logistic-normal moments, tabulated): the same objective, with less Monte-Carlo noise and no colour draws (gaussian_likelihood_nll)."""
    kl: Literal["none", "fixed_prior", "full"] = "full"
    """KL terms (paper Table 3): none, fixed-prior (random points) only, or full (random + observed-ray priors)."""
    kl_estimator: Literal["closed_form", "monte_carlo"] = "closed_form"
    """Exact KL or the paper's Monte-Carlo estimate."""
    kl_mc_samples: int = 8
    """Draws per point for the Monte-Carlo KL. Range: an integer >= 1 and <= 4096."""
    lambda_random: float = 1e-2
    """Weight of the mean KL over random scene points. Range: a finite number >= 0."""
    lambda_observed: float = 1.25e-2
    """Weight of the mean KL over the training-ray samples. Default 1.25e-2, a quarter of the earlier default 5e-2 (the paper states no weight; the tables' paper S-NeRF rows keep 5e-2): the shared observed prior pulls every observed point's variance towards one value, and at a quarter of its weight the recalibrated depth intervals came closer to nominal on every scene (benchmarks/results/uncertainty_study/kl, study 16b). Range: a finite number >= 0."""
    random_points_per_axis: int = 12
    """Stratified random KL points: n per axis, n^3 points per step. Range: an integer >= 1 and <= 256."""
    observed_kl_samples: int = 4096
    """Training-ray samples per step on which the observed-prior KL is evaluated (a uniform random subset: an unbiased estimate of the mean over all samples at a fraction of the cost; 0 = all). Range: an integer >= 0 and <= 16777216."""
    noise_head_decoupled: bool = True
    """With loss.per_point_noise: the noise head only explains residuals. Each pixel-draw term of the likelihood is weighted by stopgrad(v / sigma_n^2) and v uses stopgrad(w), so colours and densities get exactly the gradient of the global-noise likelihood, while beta still fits the residuals (stationary at v = r^2; beta-NLL, Seitzer et al. 2022). Off: the joint likelihood, where a large beta also down-weights a pixel for the colours and the geometry (it cost up to 1.2 dB PSNR in benchmarks/results/uncertainty_study/noise_head)."""
    per_point_noise: bool = True
    """Learn an observation-noise std beta(x) per point (one more field output) beside sigma_n: each trajectory's pixel likelihood gets variance sigma_n^2 + sum_i w_i beta_i^2, and with render.colour_variance='predictive' the rendered colour variance adds its mean over draws (docs/definitions.md §4.7). Default on: benchmarks/results/uncertainty_study/noise_head. Off: one noise for every pixel (sigma_n), the paper's model."""
    lambda_depth: float = 1.0
    """Weight of the sparse-depth likelihood of the capture's own structure-from-motion points (FIT role of the spatial split, stochastic_fields.capture_points): -mean_k log sum_i w_ik N(t* | t_i, s_i^2) per point ray (termination_depth_nll). 0 = off (the paper); scenes without capture points train without it. Default 1.0: benchmarks/results/uncertainty_study (0.1 in study 1, 0.3 in study 4, geometry, 1.0 in study 6, depth_weight); 3.0 made the paper split's depth closer (abs-rel -8% / -15%) but lowered flower's depth ranking 0.685 -> 0.642 (benchmarks/results/depth_weight_paper_study, study 40). Range: a finite number >= 0."""
    depth_rays_per_batch: int = 256
    """Capture-point rays per training step for the depth likelihood (drawn from the training views' FIT points). Range: an integer >= 1 and <= 1048576."""
    depth_relative_std: float = 0.03
    """Depth noise of a capture point relative to its depth (added to each sample's bin width in the depth likelihood). Default 0.03 (0.01 before study 35): on the validation scenes depth abs-rel 0.0232 -> 0.0226, CRPS / depth 0.0162 -> 0.0159 and the depth ranking 0.454 -> 0.490 at +0.05 dB, flower's capture abs-rel 0.0576 -> 0.0550, fern's unchanged (benchmarks/results/point_noise_study). Range: a finite number > 0."""
    depth_likelihood: Literal["expected", "predictive"] = "expected"
    """How the depth likelihood combines the K trajectories of a capture-point ray: 'expected' (the ELBO's expected log-likelihood, -1/K sum_k log p(t* | w_k): every trajectory must put mass at the point) or 'predictive' (the log of the predictive mixture, -log 1/K sum_k p(t* | w_k): the trajectories together must, so they may disagree where the data do not decide; a proper scoring rule on the predictive termination distribution, as predictive / PAC^2 variational objectives, Masegosa 2020). The two are equal for K = 1 (termination_depth_nll). Default 'expected': 'predictive' changed nothing on the validation scenes, whose trajectories agree at the capture points to 0.03-0.08% of the depth (docs/studies.md, study 34)."""
    depth_outlier_share: float = 0.0
    """The share eps of capture points the depth likelihood treats as possible outliers of the structure from motion: each point's likelihood under a trajectory is (1 - eps) sum_i w_i N(t* | t_i, s_i^2) + eps / L, L the ray's sampled range (termination_depth_nll), so a point far from the rendered surface pulls on it less the farther it lies (a heavy-tailed likelihood). 0 = the Gaussian mixture alone (the default): at 0.05 the paper split's depth got worse (flower's abs-rel 0.113 -> 0.122, PSNR -0.11 / -0.12 dB on fern / flower; benchmarks/results/depth_outlier_paper_study, study 41). Range: a finite number >= 0 and < 1."""
    head_bootstrap_keep: float = 1.0
    """With density heads (``field.density_heads`` M > 1): the chance that a head keeps a training pixel in its likelihood, drawn once per pixel and head for the whole training (a bootstrap of the pixels per head, as Bootstrapped DQN's heads, Osband et al. 2016), so that the heads fit different subsets of the photos and may hold different surfaces where the photos leave them open. A pixel no head keeps goes to one head drawn at random, and a pixel's weights are M / (heads keeping it) for the heads that keep it: each pixel's total weight in the loss is unchanged and each head's mean weight is 1 (losses.bootstrap_head_weights). 1 = every head fits every pixel (the default): at 0.5 the heads disagreed more but not where the depth was wrong, flower's paper-split depth ranking fell 0.622 -> 0.598 and fern's intervals widened (benchmarks/results/head_bootstrap_study, study 55). The sparse-depth likelihood's points train every head. Range: a finite number > 0 and <= 1."""
    depth_trains_scale: bool = True
    """Whether the sparse-depth likelihood's gradient reaches the density's scale s_a. On (the ELBO): the likelihood asks every trajectory to stop at each capture point, which shrinks the density's scale at the surfaces until the K trajectories agree. Off: its trajectories are drawn with stopgrad(s_a), so the capture points place the surfaces through the density's location mu_a only and the scale is set by the pixels and the priors. Off changed nothing measurable on a validation scene (benchmarks/results/predictive_depth_study/objective_knobs): the sharp surfaces, not the scale's gradient, keep the trajectories together."""
    depth_final_factor: float = 1.0
    """The sparse-depth likelihood's weight at the end of training relative to loss.lambda_depth: the weight falls linearly with the schedule's progress (steps, or the minutes budget) from lambda_depth to lambda_depth * depth_final_factor. 1 = constant (the default); 0 = the points place the surfaces early and leave the density's scale to the pixels late (on a validation scene: depth ranking 0.500 -> 0.543 at -0.09 dB, trajectories still within 0.13% of the depth; benchmarks/results/predictive_depth_study/objective_knobs). Range: a finite number >= 0 and <= 1."""
    depth_draws: int = 0
    """Trajectories per capture-point ray in the depth likelihood (0: ``train.train_draws``, as the colour rays). Range: an integer >= 0 and <= 4096."""
    lambda_distortion: float = 0.0
    """Weight of the Mip-NeRF 360 distortion regulariser on every training trajectory (stochastic_fields.distortion): penalises weight spread along rays (floaters). 0 = off (the paper's objective); on fern at 1000 steps it did not empty space for skipping and cost PSNR at weight 20 (docs/design.md); on the captures (3300 steps, one seed) weight 2 lowered fern's depth abs-rel 6% with a 9% higher 95% interval score and moved flower not at all, weight 8 lost 0.2-0.3 dB and widened flower's depth bands 2.3x (docs/studies.md, 'Measurement: the distortion regulariser on a capture'). Range: a finite number >= 0."""
    lambda_occlusion: float = 0.0
    """Weight of the occlusion regulariser (stochastic_fields.occlusion, after FreeNeRF): the mean over training rays of the expected optical depth in the near loss.occlusion_near_fraction of each ray's sampled range, against surfaces floating in front of the cameras that render pixels on the wrong surface. Every model applies it to its training rays (S-NeRF to the expected density, the mean-field baselines to their density). 0 = off (the paper's objective); the llff preset (forward-facing scenes) sets 0.1: on the paper split's validation photos (fresh seeds 7-9) S-NeRF gained 0.56 / 0.31 dB on fern / flower, depth abs-rel 0.120 -> 0.102 / 0.111 -> 0.100, and a median 95% depth band of 16.8% / 18.3% of the depth instead of 23.2% / 23.9%, every level held as before (benchmarks/results/occlusion_study, study 29). Untested on scenes around an object, where the near part of a ray may hold the object. Range: a finite number >= 0."""
    occlusion_near_fraction: float = 0.25
    """The near part of each ray the occlusion regulariser covers, as a fraction of the sampled range in the sampling coordinate (disparity for render.spacing='disparity'): 0.25 = the first 16 of 64 samples. Range: a finite number > 0 and <= 1."""
    lambda_smoothness: float = 0.0
    """Weight of the unseen-view depth smoothness regulariser (stochastic_fields.depth_smoothness, after RegNeRF): each step renders loss.smoothness_patches patches of loss.smoothness_patch_size^2 pixels from virtual cameras between neighbouring training views (stochastic_fields.virtual_views) with the expected density, and penalises the squared differences of neighbouring pixels' expected depths in the sampling coordinate (normalised to [0, 1]). Every model applies it (S-NeRF to the expected density, the mean-field baselines to their density). 0 = off (the paper's objective, and every preset's): at weight 60 on the paper split's validation photos (seeds 7-9) S-NeRF's depth abs-rel fell 0.102 -> 0.092 (fern) and 0.100 -> 0.080 (flower) and fern's median 95% band 16.8% -> 14.8% of the depth, but flower's band widened (18.3% -> 18.6%, its depth ranking 0.669 -> 0.596) and its deterministic NeRF lost 0.11 dB (benchmarks/results/smoothness_study, study 31). Range: a finite number >= 0."""
    smoothness_patches: int = 8
    """Patches the depth smoothness regulariser renders per training step (loss.lambda_smoothness > 0). Range: an integer >= 1 and <= 4096."""
    smoothness_patch_size: int = 8
    """Side of each depth smoothness patch, in pixels of the training images (8: 64 rays a patch). Range: an integer >= 2 and <= 64."""


    def __post_init__(self) -> None:
        check_fields(self, LOSS_CHECKS)


def _loss_checks() -> dict:
    """Declared range of every LossConfig field (checked on construction, load and CLI overrides)."""
    return {
        "likelihood_std": real(0.0, lo_open=True),
        "learn_likelihood_std": boolean(),
        "per_point_noise": boolean(),
        "noise_head_decoupled": boolean(),
        "likelihood_estimator": choice("draws", "rao_blackwell"),
        "kl": choice("none", "fixed_prior", "full"),
        "kl_estimator": choice("closed_form", "monte_carlo"),
        "kl_mc_samples": integer(1, 4096),
        "lambda_random": real(0.0),
        "lambda_observed": real(0.0),
        "random_points_per_axis": integer(1, 256),
        "observed_kl_samples": integer(0, 2**24),
        "lambda_depth": real(0.0),
        "depth_rays_per_batch": integer(1, 2**20),
        "depth_relative_std": real(0.0, lo_open=True),
        "depth_likelihood": choice("expected", "predictive"),
        "depth_outlier_share": real(0.0, 1.0, hi_open=True),
        "depth_draws": integer(0, 4096),
        "depth_trains_scale": boolean(),
        "head_bootstrap_keep": real(0.0, 1.0, lo_open=True),
        "depth_final_factor": real(0.0, 1.0),
        "lambda_distortion": real(0.0),
        "lambda_occlusion": real(0.0),
        "occlusion_near_fraction": real(0.0, 1.0, lo_open=True),
        "lambda_smoothness": real(0.0),
        "smoothness_patches": integer(1, 4096),
        "smoothness_patch_size": integer(2, 64),
    }


LOSS_CHECKS = _loss_checks()


#: RenderSettings.colour_estimator values: drawn colours (docs/definitions.md §3) or Rao-Blackwellised colours.
COLOUR_ESTIMATORS: tuple[str, ...] = ("draws", "rao_blackwell")



@dataclass
class RenderSettings:
    """How rays are rendered. Every field is a CLI option."""

    num_samples: int = 64
    """Samples per ray (bins between near and far). Range: an integer >= 2 and <= 100000."""
    num_draws: int = 8
    """K: stochastic trajectories per ray when rendering (training uses TrainConfig.train_draws). 8 since study 7 (docs/uncertainty.md): with Rao-Blackwellised colours the scores at K = 8 matched K = 16 with drawn colours on every scene, at 0.66x the render time. Range: an integer >= 1 and <= 4096."""
    quadrature: Literal["alpha", "trapezoid"] = "alpha"
    """Volume-rendering quadrature: 'alpha' compositing (default, measured more accurate on steep densities) or the paper's 'trapezoid'."""
    spacing: Spacing = "linear"
    """Sample spacing along rays: 'linear' in distance or linear in 'disparity' (forward-facing scenes)."""
    shared_noise: bool = False
    """Share eps along each ray per draw (trajectory-consistent draws) instead of independent eps per point."""
    chunk_rays: int = 2048
    """Rays per chunk when rendering full images (memory bound: chunk * S * K floats). Range: an integer >= 1 and <= 16777216."""
    background: tuple[float, float, float] | None = None
    """Background colour composited behind the scene. None: the scene's own (a Blender/nerfstudio file's "background", white for RGBA photos: what the photos were composited on), none (black) for a scene without one (LLFF, COLMAP, RGB photos). Range: None or three numbers in [0, 1] (r,g,b)."""
    skip_empty_space: bool = True
    """S-NeRF: keep an occupancy grid (in the scene region's unit cube), updated from the density upper estimate relu(mu_a + n s_a) (n = occupancy_num_std), and evaluate the field only at samples in occupied cells (training and rendering; needs quadrature='alpha'; set false to use 'trapezoid'). Default on: benchmarks/results measures fewer field evaluations per ray and faster training steps at equal PSNR."""
    occupancy_num_std: float = OCCUPANCY_UPPER_NUM_STD
    """Occupancy upper estimate relu(mu_a + n s_a): n standard deviations (3: a draw exceeds it with probability 0.13%). Smaller n skips more of the space S-NeRF is unsure about, at a cost in uncertainty (benchmarks/results). Range: a finite number >= 0."""
    occupancy_alpha_threshold: float = OCCUPANCY_ALPHA_THRESHOLD
    """A cell is occupied where the upper estimate gives one render interval an opacity above this. Range: a finite number > 0 and < 1."""
    occupancy_resolution: int = 64
    """Cells per axis of the occupancy grid over the region's unit cube. Range: an integer >= 1 and <= 512."""
    occupancy_update_every: int = 16
    """Training steps between occupancy-grid updates. Range: an integer >= 1 and <= 1000000000."""
    occupancy_warmup_steps: int = 256
    """Steps during which every occupancy cell is re-evaluated at each update (afterwards a random subset). Range: an integer >= 0 and <= 1000000000."""
    colour_variance: Literal["epistemic", "predictive"] = "predictive"
    """S-NeRF colour variance: 'predictive' (default) adds sigma_n^2 to the variance over the K trajectories; 'epistemic' is that variance alone (docs/definitions.md §3, the paper). 'predictive' adds sigma_n^2, the likelihood's pixel noise (the model's predictive variance of an observed pixel; learn sigma_n with loss.learn_likelihood_std)."""
    adaptive_draws: bool = False
    """Render with adaptive K (stochastic_fields.adaptive): trajectories in batches of adaptive_batch_draws until the colour and depth variance estimates change by less than adaptive_rtol, at most adaptive_max_draws. Used when no explicit num_draws is asked for."""
    adaptive_batch_draws: int = 8
    """Adaptive K: trajectories drawn per batch (one field evaluation serves every batch). Range: an integer >= 2 and <= 4096."""
    adaptive_max_draws: int = 128
    """Adaptive K: cap on the trajectories per ray. Range: an integer >= 2 and <= 4096."""
    adaptive_rtol: float = 0.05
    """Adaptive K: tolerance of adaptive_rule ('precision': predicted relative change of the mean precision 1/var between the current K and the cap; 'change': relative L1 change of the per-pixel colour and depth variances from one batch to the next). Measured (benchmarks/results): with colour_estimator='rao_blackwell', precision at 0.01 ends within 2% of the cap's NLL in about 0.7x its time. Range: a finite number > 0."""
    colour_estimator: Literal["draws", "rao_blackwell"] = "rao_blackwell"
    """Rendering colour statistics: 'rao_blackwell' (default since study 7) draws only densities and integrates each trajectory's colour noise exactly given its weights (E[C_k|w_k] = sum_i w_ik E[r_i], Var[C_k|w_k] = sum_i w_ik^2 Var[r_i], tabulated logistic-normal moments), estimating the same mean and variance as drawn colours with less Monte-Carlo noise and no colour draws; 'draws' samples every colour (docs/definitions.md §3: C_k = sum_i w_ik r_ik, variance over k; per-draw colour maps are then samples, not conditional means). Training always draws colours."""
    colour_min_transmittance: float = COLOUR_MIN_TRANSMITTANCE
    """Decode a sample's colour only where some trajectory has density there and reaches it with transmittance at least this (alpha quadrature; training and rendering, every method alike). Every trajectory's colour then differs from the full sum by less than this (a sample without density weighs exactly 0; the weights of the samples reached with less sum to less than it); densities, weights, depths and opacities are exact. 1e-4 since study 46b (docs/studies.md): a capture's ten CPU-minutes make 1.4-1.8x the training steps, PSNR +0.2 to +0.6 dB (two seeds). 0: every sample's colour is decoded (runs saved before the option). Range: a finite number >= 0 and < 1."""
    adaptive_rule: Literal["precision", "change"] = "precision"
    """Adaptive K stopping rule: 'precision' stops when the small-K bias of 1/var left before the cap, predicted from the draws' kurtosis, is below adaptive_rtol (aims at the NLL of K = adaptive_max_draws); 'change' when the variances change by less than adaptive_rtol between batches (stops earlier, NLL measured 4% above K = 128's at rtol 0.05). See stochastic_fields.adaptive."""
    depth_estimate: Literal["mean", "median"] = "mean"
    """S-NeRF: the depth map's point estimate of each pixel's predictive depth distribution (the mixture over the K trajectories of each one's termination distribution along the ray, stochastic_fields.termination): 'mean' its mean, the mean over k of the expected termination depths D_k (the paper's); 'median' its median F^-1(1/2), which stays on a surface where a pixel's trajectories split their mass between a near and a far one (the mean lies between them). The depth std stays the mixture's total std (about its mean); the calibration's depth map is fitted on the errors of the estimate the run renders, so recalibrate after changing it. Not with adaptive_draws. See docs/uncertainty.md."""

    def __post_init__(self) -> None:
        check_fields(self, RENDER_CHECKS)


#: Declared range of every RenderSettings field (checked on construction, load and CLI overrides).
RENDER_CHECKS: dict[str, Checker] = {
    "num_samples": integer(2, 100_000),
    "num_draws": integer(1, 4096),
    "quadrature": choice("alpha", "trapezoid"),
    "spacing": choice("linear", "disparity"),
    "shared_noise": boolean(),
    "chunk_rays": integer(1, 2**24),
    "background": colour_or_none(),
    "skip_empty_space": boolean(),
    "occupancy_num_std": real(0.0),
    "occupancy_alpha_threshold": real(0.0, 1.0, lo_open=True, hi_open=True),
    "occupancy_resolution": integer(1, 512),
    "occupancy_update_every": integer(1, 10**9),
    "occupancy_warmup_steps": integer(0, 10**9),
    "colour_variance": choice("epistemic", "predictive"),
    "adaptive_draws": boolean(),
    "adaptive_batch_draws": integer(2, 4096),
    "adaptive_max_draws": integer(2, 4096),
    "adaptive_rtol": real(0.0, lo_open=True),
    "colour_estimator": choice(*COLOUR_ESTIMATORS),
    "adaptive_rule": choice("precision", "change"),
    "colour_min_transmittance": real(0.0, 1.0, hi_open=True),
    "depth_estimate": choice("mean", "median"),
}
