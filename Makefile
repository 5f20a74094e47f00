# Two commands for a fresh machine: `make demo` and `make test`.
#
# A virtualenv is created (or reused) in $(VENV) with --system-site-packages, on purpose: a torch installed for the
# whole machine (a CUDA build on a GPU box, several GB) is used as it is instead of being installed again. The price:
# a package installed system-wide can hide one that pyproject.toml forgets to declare. .ci/install-check catches
# that (a wheel installed into a virtualenv without system packages, run from outside the clone; part of .ci/run).
#
# torch is installed only when missing, as $(TORCH_WHEEL): on Linux the CPU build (PyPI's Linux wheels are CUDA
# builds of several GB), found where pip already looks (a wheel cache, find-links, a mirror) or else on PyTorch's
# CPU index; elsewhere PyPI's build (CPU, or Metal on macOS). `make torch PY=<python>` installs it into any
# environment (.ci/install-check uses it).
PYTHON ?= python3
VENV ?= .venv
PY ?= $(VENV)/bin/python
TORCH_VERSION ?= 2.13.0
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
ifeq ($(shell uname -s),Linux)
TORCH_WHEEL ?= torch==$(TORCH_VERSION)+cpu
else
TORCH_WHEEL ?= torch==$(TORCH_VERSION)
endif
DEMO_STAMP := $(VENV)/.pi0-torch-envs-installed
DEV_STAMP := $(VENV)/.pi0-torch-dev-installed

.PHONY: install torch demo test test-slow test-gpu bench clean

$(VENV)/bin/python:
	$(PYTHON) -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --upgrade pip

torch:
	@$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q "$(TORCH_WHEEL)" 2>/dev/null \
		|| $(PY) -m pip install -q "$(TORCH_WHEEL)" --extra-index-url $(TORCH_CPU_INDEX)

# make demo: the package with the envs extra (gymnasium, PyAV)
$(DEMO_STAMP): pyproject.toml | $(VENV)/bin/python
	$(MAKE) --no-print-directory torch
	$(PY) -m pip install -q -e ".[envs]"
	touch $@

# make test: every extra and the test tools
$(DEV_STAMP): pyproject.toml | $(VENV)/bin/python
	$(MAKE) --no-print-directory torch
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

install: $(DEV_STAMP)

demo: $(DEMO_STAMP)
	$(PY) examples/demo.py

# Every test file runs, whatever fails before it, and one summary closes the run (tests/suite.py: the serving tests in a
# process of their own). --timeout only turns a hang into a failure: 30 minutes for one test, which no test comes near
# even on a loaded 2-core machine (the whole suite: about 10 minutes there).
TEST_TIMEOUT ?= 1800
test: $(DEV_STAMP)
	$(PY) tests/suite.py --timeout $(TEST_TIMEOUT)

test-slow: $(DEV_STAMP)
	$(PY) -m pytest -q -m "slow" tests

# On a CUDA machine: the fixtures on the GPU (float32 and bf16), the sampling as CUDA graphs, varlen attention, FSDP,
# and the fused kernels on real hardware (tests/test_kernels.py). A GPU image without network (no pip install):
# tests/test_cuda.py and tests/test_kernels.py with $(PYTHON) as it is (torch, triton, transformers, safetensors and
# pytest are all they need). benchmarks/gpu_check.sh runs this, the doctor and the benchmark as one bounded command.
test-gpu:
	@if $(MAKE) --no-print-directory $(DEV_STAMP); then $(PY) -m pytest -q -m "gpu" tests && $(PY) -m pytest -q tests/test_kernels.py; \
	else echo "test-gpu: the [dev] extra could not be installed (no network?): the GPU tests with $(PYTHON) as it is"; \
		$(PYTHON) -m pytest -q -m "gpu" -p no:cacheprovider tests/test_cuda.py && $(PYTHON) -m pytest -q -p no:cacheprovider tests/test_kernels.py; fi

bench: $(DEV_STAMP)
	$(PY) -m pi0_torch.cli bench

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
