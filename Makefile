# Two commands for a fresh machine: `make demo` and `make test`.
# A virtualenv is created (or reused) in $(VENV). It sees the system site-packages, so a torch that is already
# installed (for example a CUDA build) is kept; only when torch is missing is the CPU wheel torch==2.13.0 installed.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.pi0-torch-installed

.PHONY: install demo test test-slow test-gpu bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(PY) examples/demo.py

# The serving tests run in a process of their own: after the rest of the suite, a server thread in the same process
# was once seen stuck in torch's CPU thread pool. Not reproduced since (the whole suite in one process, and a 6-minute
# load of 13,824 requests after other torch work, both passed). The timeout turns any hang into a failure quickly.
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow and not gpu" --timeout 900 --doctest-modules pi0_torch tests --ignore tests/test_serving.py --ignore tests/test_pi0_fast_serving.py
	$(PY) -m pytest -q -m "not slow and not gpu" --timeout 300 tests/test_serving.py tests/test_pi0_fast_serving.py

test-slow: $(STAMP)
	$(PY) -m pytest -q -m "slow" tests

# On a CUDA machine: the fixtures on the GPU (float32 and bf16) and the sampling as one CUDA graph.
test-gpu: $(STAMP)
	$(PY) -m pytest -q -m "gpu" tests

bench: $(STAMP)
	$(PY) -m pi0_torch.cli bench

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
