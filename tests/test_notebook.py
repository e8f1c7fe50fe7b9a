"""notebooks/inspect_run.ipynb: committed without outputs, and executable top to bottom.

The notebook is executed headless with nbclient: it is the minimal executor (the library that
nbconvert, papermill and nbmake all run on), needs no pytest plugin, and runs inside an ordinary
test against a run that a fixture trains in a few seconds. Its kernel is this interpreter, named
by a kernelspec written into a temporary JUPYTER_PATH, so the test does not depend on which
kernels a machine has installed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "inspect_run.ipynb"
KERNEL_NAME = "stochastic-fields-test"
#: Seconds a single cell may run before nbclient fails the test (the tiny run renders a 64x48
#: view in about a second; this bounds a hung kernel, it is not a timing assertion).
CELL_TIMEOUT_S = 300


def _load():
    import nbformat

    return nbformat.read(NOTEBOOK, as_version=4)


def test_committed_notebook_has_no_outputs():
    nb = _load()
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code, "the notebook has no code cells"
    for i, cell in enumerate(code):
        assert cell.outputs == [], f"code cell {i} has stored outputs: strip them before committing"
        assert cell.execution_count is None, f"code cell {i} has an execution count"
    assert "widgets" not in nb.metadata, "stored widget state: strip it before committing"


def test_parameters_cell_reads_the_run_from_the_environment():
    nb = _load()
    first = next(c for c in nb.cells if c.cell_type == "code")
    assert "parameters" in first.metadata.get("tags", [])
    assert 'RUN_DIR = os.environ.get("STOCHASTIC_FIELDS_RUN", "../runs/demo")' in first.source
    from stochastic_fields.inspect import RUN_ENV_VAR

    assert RUN_ENV_VAR == "STOCHASTIC_FIELDS_RUN"


# --------------------------------------------------------------------------- execution
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, tiny_scene) -> Path:
    """A few seconds of S-NeRF training on the 64x48 test scene (see tests/test_inspect.py)."""
    from stochastic_fields.config import preset
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer

    run_dir = tmp_path_factory.mktemp("notebook_run")
    cfg = preset("tiny")
    cfg.data.path = str(tiny_scene)
    cfg.train.iterations = 10
    cfg.train.rays_per_batch = 128
    cfg.train.lr = 5e-2
    cfg.train.tv_weight = 0.0
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    Trainer(cfg, run_dir, load_run_dataset(cfg, run_dir)).train(progress=False)
    return run_dir


@pytest.fixture(scope="module")
def kernel_env(tmp_path_factory):
    """A kernelspec for this interpreter in a temporary JUPYTER_PATH (and a clean IPython profile)."""
    root = tmp_path_factory.mktemp("jupyter")
    spec_dir = root / "kernels" / KERNEL_NAME
    spec_dir.mkdir(parents=True)
    spec = {"argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
            "display_name": "stochastic-fields (test)", "language": "python"}
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("JUPYTER_PATH", str(root))
        mp.setenv("IPYTHONDIR", str(root / "ipython"))
        mp.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
        yield mp


def _execute(env: pytest.MonkeyPatch, run_dir: Path, static: bool):
    from nbclient import NotebookClient
    from nbclient.output_widget import OutputWidget

    class CapturingOutputWidget(OutputWidget):
        """nbclient's Output-widget mimic, without echoing its outputs back to the kernel.

        The stock mimic sends every captured output back over the shell channel while the
        client is waiting on that channel for the execute reply; with a large output (a
        plotly cloud) the reply can then sit unseen until the cell timeout expires, silently.
        The kernel does not need the echo; the outputs are still recorded in the widget state.
        """

        def sync_state(self) -> None:
            pass

    env.setenv("STOCHASTIC_FIELDS_RUN", str(run_dir))
    env.setenv("STOCHASTIC_FIELDS_STATIC", "1" if static else "0")
    nb = _load()
    client = NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name=KERNEL_NAME,
                            resources={"metadata": {"path": str(NOTEBOOK.parent)}})
    client.widget_registry["@jupyter-widgets/output"]["OutputModel"] = CapturingOutputWidget
    client.execute()  # raises CellExecutionError on the first failing cell
    return nb


def _all_outputs(nb) -> list[dict]:
    """Outputs of every cell plus those captured by Output widgets (where widget callbacks draw)."""
    outs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    state = nb.metadata.get("widgets", {}).get("application/vnd.jupyter.widget-state+json", {}).get("state", {})
    for model in state.values():
        outs.extend(model.get("state", {}).get("outputs", []))
    return outs


def _mime_count(outs, mime: str) -> int:
    return sum(mime in o.get("data", {}) for o in outs)


def _assert_no_errors(outs):
    errors = [o for o in outs if o.get("output_type") == "error"]
    assert not errors, "\n".join(f"{e['ename']}: {e['evalue']}" for e in errors)
    streams = "".join(o.get("text", "") for o in outs if o.get("name") == "stderr")
    assert "Traceback" not in streams, streams


@pytest.mark.slow
def test_notebook_runs_with_widgets(tiny_run, kernel_env):
    nb = _execute(kernel_env, tiny_run, static=False)
    outs = _all_outputs(nb)
    _assert_no_errors(outs)
    text = "".join(o.get("text", "") for o in outs)
    assert str(tiny_run) in text  # the summary names the run the parameter pointed at
    # overview + map + probe + sparsification + calibration are PNGs; the cloud is a plotly figure
    assert _mime_count(outs, "image/png") >= 5
    assert _mime_count(outs, "application/vnd.plotly.v1+json") == 1
    assert _mime_count(outs, "application/vnd.jupyter.widget-view+json") == 4  # four panels of controls
    assert "psnr" in text and "points from views" in text


@pytest.mark.slow
def test_notebook_runs_static(tiny_run, kernel_env):
    nb = _execute(kernel_env, tiny_run, static=True)
    outs = _all_outputs(nb)
    _assert_no_errors(outs)
    assert "widgets" not in nb.metadata
    # overview, map, probe, static 3D cloud, sparsification, calibration, depth intervals: all in the cells
    assert _mime_count(outs, "image/png") == 7
    assert _mime_count(outs, "application/vnd.plotly.v1+json") == 0
