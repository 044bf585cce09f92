# The two commands a new user runs: `make demo` and `make test`. Both work from a fresh clone.
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
DEMO_OUT ?= demo_out

.PHONY: install system test test-export lint demo clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch goes in first and pinned: an unpinned torch pulls a CUDA build of several GB.
$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/pip install "$(TORCH)"
	$(BIN)/pip install -e ".[test]"
	touch $@

install: $(VENV)/.installed system

# open3d needs libusb-1.0 from the system.
system:
	@bash scripts/check_system.sh

lint: install
	$(BIN)/ruff check .

test: lint
	$(BIN)/python -m pytest -q

# The exporters (langfield export clip|sam|depth) need torch 2.14's ONNX exporter, open_clip,
# segment-anything and transformers: a second venv, so that .venv keeps its torch. Runs the tests
# marked `export` (tiny random models exported and checked against PyTorch).
EXPORT_VENV ?= .venv-export
EXPORT_TORCH ?= torch==2.14.1 torchvision==0.29.1
EXPORT_BIN := $(EXPORT_VENV)/bin

$(EXPORT_BIN)/python:
	$(PYTHON) -m venv $(EXPORT_VENV)

$(EXPORT_VENV)/.installed: $(EXPORT_BIN)/python pyproject.toml
	$(EXPORT_BIN)/pip install $(EXPORT_TORCH)
	$(EXPORT_BIN)/pip install -e ".[export,test]"
	touch $@

test-export: $(EXPORT_VENV)/.installed system
	$(EXPORT_BIN)/python -m pytest -q -m export

demo: install
	$(BIN)/langfield demo --out $(DEMO_OUT)

clean:
	rm -rf $(VENV) $(EXPORT_VENV) $(DEMO_OUT) .pytest_cache
