"""The render cost of ``render.depth_estimate`` "median" against "mean": one validation photo of a trained
run rendered with each, alternating, three times, on one thread (the median's bisection runs inside each
chunk's render on the same draws).

    OMP_NUM_THREADS=1 python benchmarks/studies/median_render_cost.py RUN
"""
import dataclasses, sys, time, warnings, statistics, torch
from stochastic_fields.cameras import generate_rays_for_view
from stochastic_fields.renderer import seeded_chunks
from stochastic_fields.trainer import load_trained_model
torch.set_num_threads(1)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    _, model, ds = load_trained_model(sys.argv[1], device="cpu")
v = ds.test_indices[0]
rays = generate_rays_for_view(ds.cameras, v, ds.near, ds.far)
base = model.render_settings
times = {"mean": [], "median": []}
for rep in range(3):
    for arm in ("mean", "median"):
        model.render_settings = dataclasses.replace(base, depth_estimate=arm)
        t0 = time.perf_counter()
        with torch.no_grad():
            model.render_view(rays, generator=seeded_chunks(0, v))
        times[arm].append(time.perf_counter() - t0)
print({k: [round(x, 2) for x in t] for k, t in times.items()})
print("ratio of medians", statistics.median(times["median"]) / statistics.median(times["mean"]))
