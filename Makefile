# The two commands a new user runs: `make demo` and `make test`. Both work from a fresh clone.
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
DEMO_OUT ?= demo_out
# Exact versions of everything installed (pip constraints): a fresh clone gets what was tested.
# `make lock` refreshes them from the newest releases pyproject.toml's ranges allow.
LOCK ?= locks/main.txt
EXPORT_LOCK ?= locks/export.txt

.PHONY: install system test test-fast test-export test-latest lint demo results lock clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch goes in first and pinned: an unpinned torch pulls a CUDA build of several GB. The kernels are
# compiled here, once, so that the first `langfield train` does not stop for them.
$(VENV)/.installed: $(BIN)/python pyproject.toml $(LOCK)
	$(BIN)/pip install --no-cache-dir -c $(LOCK) "$(TORCH)"
	$(BIN)/pip install --no-cache-dir -c $(LOCK) -e ".[test,cluster]"
	$(BIN)/python -c "from langfield.cli.warmup import main; main()"
	touch $@

install: system $(VENV)/.installed

# open3d needs libusb-1.0 from the system.
system:
	@bash scripts/check_system.sh

lint: install
	$(BIN)/ruff check .
	$(BIN)/lint-imports

test: lint
	$(BIN)/python -m pytest -q

# The suite without the tests marked `slow` (the longest trainings and end-to-end commands): about
# half its time, for quick checks while editing.
test-fast: lint
	$(BIN)/python -m pytest -q -m "not slow"

# The exporters (langfield export clip|sam|depth) need torch 2.14's ONNX exporter, open_clip,
# segment-anything and transformers: a second venv, so that .venv keeps its torch. Runs the tests
# marked `export` (tiny random models exported and checked against PyTorch).
EXPORT_VENV ?= .venv-export
EXPORT_TORCH ?= torch==2.14.1 torchvision==0.29.1
EXPORT_BIN := $(EXPORT_VENV)/bin

$(EXPORT_BIN)/python:
	$(PYTHON) -m venv $(EXPORT_VENV)

$(EXPORT_VENV)/.installed: $(EXPORT_BIN)/python pyproject.toml $(EXPORT_LOCK)
	$(EXPORT_BIN)/pip install --no-cache-dir -c $(EXPORT_LOCK) $(EXPORT_TORCH)
	$(EXPORT_BIN)/pip install --no-cache-dir -c $(EXPORT_LOCK) -e ".[export,test]"
	touch $@

test-export: system $(EXPORT_VENV)/.installed
	$(EXPORT_BIN)/python -m pytest -q -m export

demo: install
	$(BIN)/langfield demo --out $(DEMO_OUT)

# docs/results.md from the benchmark specs (benchmarks/*.toml): each runs as a sweep into results/NAME
# (finished runs are kept, so a second call resumes), then the page is rewritten. The real scenes are
# ../shared/data beside the clone; each trains for 10-15 minutes on 2 cores.
results: install
	$(BIN)/langfield results

# Refreshes both locks from the newest releases the ranges allow, in throwaway venvs; run the suite
# (`make test test-export`) before committing the new locks.
lock:
	bash scripts/lock.sh "$(PYTHON)" "$(TORCH)" "[test,cluster]" $(LOCK)
	bash scripts/lock.sh "$(PYTHON)" "$(EXPORT_TORCH)" "[export,test]" $(EXPORT_LOCK)

# The newest releases, unlocked (not in CI): tells whether the next `make lock` will pass.
LATEST_VENV ?= .venv-latest
test-latest: system
	rm -rf $(LATEST_VENV)
	$(PYTHON) -m venv $(LATEST_VENV)
	$(LATEST_VENV)/bin/pip install "$(TORCH)"
	$(LATEST_VENV)/bin/pip install --upgrade -e ".[test,cluster]"
	$(LATEST_VENV)/bin/pip freeze --exclude-editable
	$(LATEST_VENV)/bin/ruff check .
	$(LATEST_VENV)/bin/python -m pytest -q

clean:
	rm -rf $(VENV) $(EXPORT_VENV) $(LATEST_VENV) $(DEMO_OUT) .pytest_cache
