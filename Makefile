# Two entry points for a newcomer: `make run` and `make test`. Both create the local
# virtual environment .venv on first use and install the project into it.
#
# torch is installed first, on its own, at the version in TORCH_SPEC (on these CPU
# machines 2.13.0 resolves to a local CPU wheel); every later install is constrained to
# the torch that is then present, so no dependency can replace it with a multi-GB CUDA
# build. On a CUDA machine pick your build, e.g.
#   make test TORCH_SPEC="torch==2.13.0 --index-url <the PyTorch wheel index of your CUDA>"

PYTHON     ?= python3
VENV       ?= .venv
TORCH_SPEC ?= torch==2.13.0
PY          = $(VENV)/bin/python
STAMP       = $(VENV)/.installed

.PHONY: run test test-fast bench clean-venv

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install --quiet $(TORCH_SPEC)
	$(PY) -W ignore -c "import torch; print('torch==' + torch.__version__.split('+')[0])" > $(VENV)/constraints.txt
	$(PY) -m pip install --quiet -c $(VENV)/constraints.txt -e ".[test]"
	touch $(STAMP)

# The main job, the thesis's method: Vision-KGRL on PegInsert (Factory, 4D; the quick preset on a
# CPU, the thesis preset on CUDA). On first use it records the demonstrations and fits the KMP
# prior, collects the camera image set and trains the VAE (all cached in runs/cache/; on a 2-core
# CPU the image set and VAE take ~30-45 min once). It ends with the policy's success, its prior's
# on the same evaluation episodes and the paired gain. Results in runs/train/<run>/ (metrics.json,
# tb/, checkpoints/). KGRL without vision: `python train/run.py --method kgrl`.
run: $(STAMP)
	$(PY) train/run.py --task PegInsert --method vision_kgrl

# the layer rules (pyproject's [tool.importlinter]: a broken one fails here), then the whole suite
test: $(STAMP)
	$(VENV)/bin/lint-imports --no-cache
	$(PY) -m pytest -q tests

# the inner loop for whoever changes the code: every package's fast tests (not the `slow` ones:
# whole training runs, the gym ids, the kernel compiles of the other solvers), a few minutes on 2 cores
test-fast: $(STAMP)
	$(VENV)/bin/lint-imports --no-cache
	$(PY) -m pytest -q -m "not slow" tests

bench: $(STAMP)
	$(PY) -m vkgrl_newton.tools.bench_kernels

clean-venv:
	rm -rf $(VENV)
