# Every target only calls pip, pytest or the spiral CLI. The virtualenv lives in .venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_VERSION := 2.13.0

.PHONY: install run test smoke bench lint clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check "torch==$(TORCH_VERSION)"
	$(BIN)/python -m pip install -q --disable-pip-version-check -e ".[test]"
	touch $(STAMP)

run: install
	$(BIN)/spiral run pipelines/full.yaml --jobs 2

# The suite's modules spread over the machine's cores (at most 4 worker processes), each module on one worker so
# that its fixtures are built once; `pytest` alone runs it in one process.
test: install
	$(BIN)/python -m pytest -n auto --maxprocesses 4 --dist loadfile

smoke: install
	$(BIN)/spiral run pipelines/smoke.yaml

bench: install
	$(BIN)/spiral bench sim --device cpu --worlds 1,64,1024,4096,16384 --json docs/bench_sim.json
	$(BIN)/spiral bench kernels --json docs/bench_kernels.json
	$(BIN)/spiral bench ppo pipelines/full.yaml --stage solo --json docs/bench_ppo.json

lint: install
	$(BIN)/ruff check spiral tests

clean:
	rm -rf $(VENV) runs
