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

.PHONY: run test bench clean-venv

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install --quiet $(TORCH_SPEC)
	$(PY) -W ignore -c "import torch; print('torch==' + torch.__version__.split('+')[0])" > $(VENV)/constraints.txt
	$(PY) -m pip install --quiet -c $(VENV)/constraints.txt -e ".[test]"
	touch $(STAMP)

# The main job on its embedded default. Until the simulator exists it fits the KMP
# prior to synthetic PegInsert demonstrations and draws the KMP bands (runs/kmp_demo/).
run: $(STAMP)
	$(PY) train/plot_kmp.py --synthetic PegInsert --out runs/kmp_demo

test: $(STAMP)
	$(PY) -m pytest -q tests

bench: $(STAMP)
	$(PY) -m vkgrl_newton.kernels.bench

clean-venv:
	rm -rf $(VENV)
