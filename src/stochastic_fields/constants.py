"""Stability constants, named and justified in one place.

Every numerical guard in the package refers to a name from this module; no bare ``1e-10``
elsewhere. Values are chosen for float32 unless stated; they are harmless in float64.
"""

from __future__ import annotations

import math

#: Smallest standard deviation a field may output (softplus(raw) + floor). Below this the
#: rectified-normal and logistic-normal KLs grow like -log(sigma) and gradients like 1/sigma;
#: 1e-4 keeps them finite in float32 while being far below any uncertainty a scene shows.
FIELD_STD_FLOOR: float = 1e-4

#: Prior standard deviation on random scene points (paper Sec. 3.2.3: "fixed to 10").
RANDOM_POINT_PRIOR_STD: float = 10.0

#: Floor of a sample's termination weight inside the log of the sparse-depth likelihood
#: (losses.termination_depth_nll): a ray whose every weight is zero still has a finite loss
#: (about -log(1e-10) = 23 nats plus the normal's log density); weights above it get the gradient.
DEPTH_MIXTURE_WEIGHT_FLOOR: float = 1e-10

#: Optical depth beyond which transmittance is treated as exactly zero when skipping work.
#: exp(-30) ~ 1e-13, below float32 resolution of any colour.
MAX_OPTICAL_DEPTH_FOR_SKIP: float = 30.0

#: Accumulated opacity above which a ray is "opaque" for early termination in rendering loops.
#: Derived from MAX_OPTICAL_DEPTH_FOR_SKIP: 1 - exp(-30).
OPAQUE_TRANSMITTANCE: float = math.exp(-MAX_OPTICAL_DEPTH_FOR_SKIP)

#: Divisor floor when normalising depth by accumulated opacity (expected depth given a hit).
#: Relative to opacity in [0, 1]; an opacity below this is a ray that hit nothing.
OPACITY_EPS: float = 1e-6

#: Minimum variance used by the Gaussian NLL metric (docs/definitions.md §6): colours are 8-bit, so a variance
#: below (1/255)^2 / 12 (uniform quantisation noise) claims more than the data can hold.
NLL_VARIANCE_FLOOR: float = (1.0 / 255.0) ** 2 / 12.0

#: Probability clamp for logit() of colours in [0, 1] (8-bit data never reaches 0 or 1 exactly
#: in a meaningful way): half of one 8-bit step away from the ends.
COLOUR_PROB_CLAMP: float = 0.5 / 255.0

#: Stand-in for an unbounded last interval in alpha compositing when no far plane is given.
FAR_INTERVAL: float = 1e10

#: Minimum depth variance (scene units squared) used by the depth NLL metric (docs/definitions.md §6). Same
#: reasoning as NLL_VARIANCE_FLOOR: a renderer cannot resolve depth finer than its sample spacing
#: delta, whose uniform quantisation variance is delta^2 / 12. The finest plausible sampling in our
#: data (Blender lego, depth range [2, 6], 1024 samples per ray) has delta ~ 4e-3, i.e.
#: delta^2 / 12 ~ 1.3e-6; we round to 1e-6 (std 1e-3 scene units). LLFF scenes in COLMAP units
#: (near ~ 17) are coarser, so the floor never binds there unless a model claims sub-resolution
#: certainty. It is in absolute units: pass var_floor * scale**2 if a scene is rescaled.
DEPTH_NLL_VARIANCE_FLOOR: float = 1e-6

#: density_loc a field reports outside its modelled region: relu(loc + scale * eps) is then 0
#: for any draw within 1e3 standard deviations, i.e. empty space.
OUTSIDE_DENSITY_LOC: float = -1e4

#: Truncated-normal moments of Y ~ N(z, 1) given Y > 0 (rectified-normal mean/variance/KL):
#: below z = -MILLS_CF_SWITCH the direct formulas kappa = z + phi/Phi and
#: var = 1 - (phi/Phi) * kappa cancel (relative error grows like eps * z^2 in kappa and
#: eps * z^4 in var), so Laplace's continued fraction for the Mills ratio is used instead.
#: At z = -3 the direct formulas lose ~300x eps (4e-5 relative in float32); the fraction, cut at
#: MILLS_CF_DEPTH terms and started from its asymptotic tail, is at float64 round-off there
#: (5e-15 relative, checked against mpmath at 40 digits) and converges faster deeper in the tail.
#: The same point is where distributions.log_ndtr switches to its erfcx form (any negative value
#: would do there; torch's log_ndtr gradient is fine down to about -1e3 in float32).
MILLS_CF_SWITCH: float = 3.0
MILLS_CF_DEPTH: int = 40

#: Logistic-normal mean/variance: for logit std <= this, Gauss-Hermite in the Gaussian variable
#: (sigmoid is analytic in a strip of half-width pi, so the rule converges like
#: exp(-c * pi / std)); above it, the step part Phi(loc/std) is exact and the remainder
#: sigmoid - step (localised within |y| < LOGISTIC_TAIL_CUTOFF) is integrated by Gauss-Legendre.
#: At std = 1 both rules agree to 1e-15 absolute (float64).
LOGISTIC_QUADRATURE_SCALE_SWITCH: float = 1.0

#: Half-width in logit units of the window where sigmoid(y) differs from the unit step:
#: |sigmoid(y) - step(y)| = sigmoid(-|y|) < exp(-40) ~ 4e-18 outside it, below float64
#: resolution of a colour in [0, 1].
LOGISTIC_TAIL_CUTOFF: float = 40.0

#: Occupancy grid: a cell is occupied where its density upper estimate gives one render sample
#: an opacity 1 - exp(-a * step) above this. Skipping a sample of opacity alpha changes the
#: colour by at most alpha (colours in [0, 1]); across the ~40 skipped samples a ray crosses in
#: a typical 64-128 sample render the loss stays below 40 * 1e-4 = 4e-3, about one 8-bit step.
OCCUPANCY_ALPHA_THRESHOLD: float = 1e-4

#: ``render.colour_min_transmittance``'s default: a sample's colour is decoded only where some
#: trajectory has density there and reaches it with at least this transmittance, so every
#: trajectory's colour is within it of the full sum (a fortieth of an 8-bit level; study 46).
COLOUR_MIN_TRANSMITTANCE: float = 1e-4

#: Density upper estimate for occupancy updates: relu(mu_a + n * s_a) with n = 3 standard
#: deviations, exceeded by a draw with probability 1 - Phi(3) = 0.13%.
OCCUPANCY_UPPER_NUM_STD: float = 3.0

#: NeRF-W's beta_min (Martin-Brualla et al. 2021, Sec. 4.2: 0.03): floor of the rendered colour
#: standard deviation of the ``nerfw`` baseline, v = sum_i w_i beta_i^2 + beta_min^2. Without it
#: the learned-variance NLL rewards v -> 0 on well-fitted pixels and diverges (log v -> -inf);
#: 0.03 is about 8 levels of 8-bit colour, above the pixel noise of real captures.
NERFW_BETA_MIN: float = 0.03

#: Initial observation-noise std beta(x) of a field's noise head (``loss.per_point_noise``),
#: colour units: small against the learned global pixel noise (0.05 initially), which stays as the
#: floor of the rendered noise variance, so training starts from the global-noise model.
NOISE_HEAD_INIT_STD: float = 0.01

#: Floor of a point's depth variance (scene units squared) when it becomes an inverse-variance
#: weight in point-cloud fusion (products.fusion): a deterministic method or a fully collapsed
#: pixel can report variance 0, whose weight would be infinite. Same reasoning and value as
#: DEPTH_NLL_VARIANCE_FLOOR: no renderer resolves depth finer than its sample spacing (~1e-3
#: scene units at the finest sampling we use), so claims below that are not information.
PRODUCT_DEPTH_VARIANCE_FLOOR: float = DEPTH_NLL_VARIANCE_FLOOR

#: Adam's epsilon (denominator floor sqrt(v) + eps). Grid cells see few rays per step, so their
#: second moments are tiny; 1e-8 would cap their steps well below the learning rate. 1e-15 (as
#: instant-NGP) keeps Adam scale-free down to gradients of ~1e-13.
ADAM_EPS: float = 1e-15

#: Empty-space skipping packs a batch's samples (ragged layout, segmented scans) only when the
#: occupancy grid removes at least this fraction of them; otherwise the batch stays dense and the
#: few empty samples are evaluated (their opacity is below OCCUPANCY_ALPHA_THRESHOLD, so keeping
#: them changes nothing beyond the skipping tolerance). Measured on fern, where nearly every cell
#: stays occupied: the packed layout costs 1.2x (training step) to 1.35x (render) the dense one at
#: equal samples, so packing pays only once it removes more than about a quarter of them.
PACK_MIN_SKIPPED_FRACTION: float = 0.25

#: ``renderer.colour_plan`` draws all K trajectories' eps at once (to know which colours a
#: trajectory reaches before the field is read), so above this many (sample, draw) pairs it plans
#: nothing and every colour is decoded: the blocks below then bound the memory as before. A
#: training step (4096 rays, 64 samples, K = 8: 2.1M pairs) and a render chunk (2048 x 64 x 8: 1M)
#: plan; K = 128 at render does not.
COLOUR_PLAN_MAX_PAIRS: int = 2 ** 22

#: Trajectories are drawn and composited in blocks of draws holding at most this many
#: (sample, draw) pairs (renderer.draw_blocks), so a render's [R, k, S, 3] temporaries stay tens
#: of MB however large K is. Measured on fern (grid field, 2048-ray chunks of 64 samples, 2 CPU
#: cores): at K = 16 one block or four cost the same; at K = 128 blocks of 2^19 pairs render 2.3x
#: faster than one block (2^21: 2.1x, 2^23: 1.06x), the [R, K, S, 3] colours of one block falling
#: from 200 MB to 6 MB.
DRAW_BLOCK_ELEMENTS: int = 2 ** 19

#: Tabulated logistic-normal moments (logistic_normal_table, for the Rao-Blackwellised colour
#: estimator): a table over the folded, MacKay-scaled location ``a = |loc| / sqrt(1 + pi s^2/8)``
#: in [0, LOGISTIC_TABLE_A_MAX] and ``log s`` in LOGISTIC_TABLE_LOG_SCALE_RANGE, read by bilinear
#: interpolation. Measured against the quadrature (distributions._logistic_normal_moments) on
#: 2e5 random (loc in [-20, 20], log s in [-8, 8]): mean within 3.1e-6 absolute, variance within
#: 2.7e-5 absolute and 1.9e-3 relative (the worst relative errors at variances ~1e-8, far below
#: NLL_VARIANCE_FLOOR). Outside the table: a > A_MAX reads its edge (the mean is within
#: sigmoid(-16) ~ 1e-7 of 0 or 1 there); log s above the range reads the edge (as s -> inf the
#: moments depend on a alone, up to E[sigmoid'(Y)] ~ 0.4 / s in the variance: 2.5e-6 at the edge,
#: s = e^12); below it the variance follows s^2 (the delta method, v ~ sigmoid'(loc)^2 s^2) and
#: the mean reads the edge (error <= s_min^2 / 20 ~ 3e-7).
LOGISTIC_TABLE_A_MAX: float = 16.0
LOGISTIC_TABLE_A_STEP: float = 0.01
LOGISTIC_TABLE_LOG_SCALE_RANGE: tuple[float, float] = (-6.0, 12.0)
LOGISTIC_TABLE_LOG_SCALE_STEP: float = 0.05

#: Seconds a rank of a data-parallel run (stochastic_fields.distributed) waits in a collective
#: (all-reduce, barrier, rendezvous) before it fails with a DistributedError instead of hanging.
#: A rank that dies is noticed at once (its connections close); the timeout is for a rank that
#: stops answering. 30 minutes covers what rank 0 does alone while the others wait: generating
#: the embedded scene, a quick evaluation, writing a checkpoint. ``train --dist-timeout`` sets it.
DISTRIBUTED_TIMEOUT_S: float = 1800.0

#: Step (in unit-cube coordinates, which span 2 per axis) by which the grid's parallax rule
#: (fields.grid.resolution_from_parallax) moves a frustum point to measure how many pixels a unit
#: of each axis spans: small enough that the projection is linear over it (a thousandth of the
#: cube, well inside one finest voxel), large enough that float32 rounding of the pixel
#: coordinates (about 1e-5 pixel at a few hundred pixels) stays far below the motion (on LLFF
#: about 0.06 pixel along the depth axis, 0.4 across the image).
PARALLAX_PROBE_STEP: float = 1e-3

#: Floor of sin theta in the parallax term kappa d / sin theta (``parallax``): about 0.6 degrees, so
#: a point fewer than two training views see (theta 0) gets a large but finite term, 100 d kappa.
PARALLAX_MIN_SIN: float = 0.01

#: Std of the per-member density-cell noise of grid ensembles, relative to the initial mean
#: density: N(0, (0.5 mu_0)^2) per point, so about 2% of points start below zero. The grid's
#: density heads (``field.density_heads``) start their offsets with the same noise.
ENSEMBLE_GRID_DENSITY_NOISE: float = 0.5
