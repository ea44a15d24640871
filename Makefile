# Set-up is part of every target: a missing .venv is created and the project
# installed into it, so `make test` and `make run` work on a fresh clone.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
export OPENBLAS_NUM_THREADS ?= 1
# numba kernels are called from several threads (worker, API): the layer must be thread-safe.
export NUMBA_THREADING_LAYER ?= threadsafe

HTTP_PORT   ?= 8000
ZENOH_LISTEN ?= tcp/127.0.0.1:7447
DATA_DIR    ?= runs
LINE        ?= configs/line.toml

.PHONY: install test run bench lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed-dev: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[dev,step]'
	touch $@

$(VENV)/.installed-bench: pyproject.toml $(VENV)/.installed-dev
	@# open3d needs the system's libusb; install it where we may.
	@ldconfig -p | grep -q 'libusb-1.0.so' || { [ "$$(id -u)" = 0 ] && \
		(apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null) || \
		echo "note: libusb-1.0 is missing; Open3D peers will be skipped"; }
	$(BIN)/python -m pip install -q -e '.[dev,step,bench]'
	touch $@

install: $(VENV)/.installed-dev

test: $(VENV)/.installed-dev
	$(BIN)/python -m pytest -q

run: $(VENV)/.installed-dev
	$(BIN)/inspection run --config $(LINE) --http-port $(HTTP_PORT) \
		--zenoh-listen $(ZENOH_LISTEN) --data-dir $(DATA_DIR)

bench: $(VENV)/.installed-bench
	$(BIN)/python -m bench $(BENCH)

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check inspection service tests bench docs
	$(BIN)/mypy inspection service

clean:
	rm -rf $(VENV) .cache .pytest_cache .mypy_cache .ruff_cache
