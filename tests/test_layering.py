"""The layers of docs/design.md ("Layers"), kept: no module imports one from a higher layer.

``LAYERS`` below is the one table of who may import whom (bottom first); imports inside
functions count too (``test_layout.import_graph``). Within a layer any import is allowed as long
as there is no cycle (``test_layout``). A new module must be placed in a layer here.
"""

from __future__ import annotations

from test_layout import import_graph

#: Bottom to top: (layer name, its modules), module names without the package prefix
#: (``stochastic_fields.`` for the library, ``bench.`` for ``stochastic_fields_bench``).
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("foundations", ("", "constants", "defaults", "validation", "io_utils", "launch", "settings", "data.errors",
                     "visualize", "holdout", "pose_alignment", "pose_check", "predictive")),
    ("geometry and maths", ("rays", "scene_region", "cameras", "distortion", "distributions", "occlusion", "depth_edges", "depth_smoothness", "logistic_normal_table",
                            "volume_rendering", "samplers", "ray_sampling", "metrics", "row_kernels", "draw_kernels", "optim", "checkpoint", "view_maps", "plots")),
    ("fields", ("fields", "fields.encoding", "fields.row_gather", "fields.base", "fields.grid", "fields.mlp")),
    ("data", ("data", "data.colmap", "data.capture", "data.dataset", "data.synthetic", "data.blender", "data.llff",
              "data.colmap_scene", "data.loading", "data.prepare", "sparse_depth", "capture_points", "virtual_views")),
    ("rendering and models", ("occupancy", "losses", "renderer", "adaptive", "config", "models", "models.base", "models.field_builder",
                              "models.snerf", "models.baselines", "models.registry", "free_space", "parallax",
                              "termination", "laplace")),
    ("runs", ("scenes", "distributed", "trainer", "calibration", "evaluation")),
    ("products", ("products", "products.free_path", "products.free_path_calibration", "products.free_space", "products.occupancy_map",
                  "products.depth_maps", "products.free_path_cli", "products.plan", "products.planner_cli",
                  "products.export_options", "products.pointcloud", "products.ros_depth", "products.fusion", "products.render_cloud",
                  "products.rosbag", "products.export", "products.rerun_log", "products.next_view",
                  "products.next_view_cli")),
    ("interfaces", ("cli", "products.cli", "inspect", "commands", "commands.calibrate", "commands.occupancy",
                    "commands.free_path", "commands.rosbag", "commands.rerun", "commands.prepare", "commands.next_view")),
    ("experiments", ("bench", "bench.bench_command", "bench.budget", "bench.methods", "bench.report", "bench.runner", "bench.speed",
                     "bench.tables")),
)


def _full_name(short: str) -> str:
    if short == "bench" or short.startswith("bench."):
        return "stochastic_fields_bench" + short[len("bench"):]
    return "stochastic_fields" + (f".{short}" if short else "")


def layer_of() -> dict[str, tuple[int, str]]:
    return {_full_name(m): (i, name) for i, (name, mods) in enumerate(LAYERS) for m in mods}


def test_every_module_has_a_layer():
    placed = layer_of()
    missing = sorted(set(import_graph()) - set(placed))
    assert not missing, f"place these modules in a layer of tests/test_layering.py (and docs/design.md): {missing}"
    gone = sorted(set(placed) - set(import_graph()))
    assert not gone, f"these modules of the layer table no longer exist: {gone}"


def test_no_module_imports_a_higher_layer():
    placed = layer_of()
    upward = []
    for module, imports in sorted(import_graph().items()):
        for target in sorted(imports):
            if module in placed and target in placed and placed[target][0] > placed[module][0]:
                upward.append(f"{module} ({placed[module][1]}) imports {target} ({placed[target][1]})")
    assert not upward, "imports against the layers of docs/design.md:\n" + "\n".join(upward)
