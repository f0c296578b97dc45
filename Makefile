# Two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
ROBOTS ?= 3
SEED ?= 0
MODE ?= distributed

.PHONY: demo test venv bench lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/kimera-multi sim sims/office.toml --robots $(ROBOTS) --seed $(SEED) --mode $(MODE) --out runs/demo --no-rerun

test: $(STAMP)
	$(BIN)/ruff check kimera_multi_py tests benchmarks
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n auto --dist loadfile --durations=15

bench: $(STAMP)
	$(BIN)/python benchmarks/sim_raycast.py --json
	$(BIN)/python benchmarks/octree_insert.py --json
	$(BIN)/python benchmarks/comms.py --json
	$(BIN)/python benchmarks/pgo.py --json
	$(BIN)/python benchmarks/allocator.py --json
	$(BIN)/python benchmarks/cli_sim.py --json
	$(BIN)/python benchmarks/pcm_clique.py --json

clean:
	rm -rf $(VENV) runs .pytest_cache
