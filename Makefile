# One-command set-up and runs. `make demo` and `make test` do everything on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
RUN ?= runs/demo

.PHONY: demo test test-slow test-all test-fast notebook bench bench-capture bench-next-view bench-registration eval-tables uncertainty-study sysdeps venv clean

$(STAMP): pyproject.toml requirements-cpu.txt scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements-cpu.txt
	$(PY) -m pip install --quiet -c requirements-cpu.txt -e ".[test,notebook]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/stochastic-fields demo --out $(RUN)

# the quick suite (a few minutes); the end-to-end tests marked slow run in test-slow (CI runs both)
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

test-all: $(STAMP)
	$(PY) -m pytest -q

test-fast: test

notebook: $(STAMP)
	$(VENV)/bin/jupyter lab notebooks/inspect_run.ipynb

# the documented speed-against-error run (about 25 minutes on 2 CPU cores; results in benchmarks/results)
bench: $(STAMP)
	$(PY) benchmarks/speed_vs_error.py --quick --iterations 1000 --mlp-iterations 150 --mlp-width 256 \
		--rays-per-batch 1024 --eval-pixels 4096 --view-stride 2 --out benchmarks/results

# quality per CPU-minute on a capture: S-NeRF and the deterministic NeRF, 10 training minutes each on fern and
# flower with the capture split (about 50 minutes on 2 CPU cores; resumable)
bench-capture: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) benchmarks/capture_quality.py --threads 2 --marks 0.25 0.5 1 --out benchmarks/results/capture_quality

# next-view selection against random, farthest-camera and ensemble choices (about 75 minutes per scene on one thread; resumable)
bench-next-view: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) benchmarks/next_view.py --scenes fern flower --work runs/next_view --out benchmarks/results/next_view

# prepare on LLFF photos without their poses, against LLFF's poses (about 15 minutes; resumable)
bench-registration: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) benchmarks/registration.py --out benchmarks/results/registration
	OMP_NUM_THREADS=1 $(PY) benchmarks/registration.py --scenes --objects lego --seeds 0 --strategies \
		--out benchmarks/results/registration_objects

# Tables 1-3 at the documented CPU budget (about 1.5 hours on 2 CPU cores; resumable)
eval-tables: $(STAMP)
	$(PY) benchmarks/eval_tables.py --scenes fern flower --timing-repeats 3 --out benchmarks/results/eval_tables

# the one-factor-at-a-time uncertainty study (about 1.5 hours on 2 CPU cores; resumable)
uncertainty-study: $(STAMP)
	$(PY) benchmarks/studies/uncertainty_study.py --out benchmarks/results/uncertainty_study

clean:
	rm -rf $(VENV) runs .pytest_cache
