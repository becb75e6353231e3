# `make install`: set up only (system libraries, the venv, drivesim and its test tools; then .venv/bin/drivesim works).
# `make demo`: `drivesim run` on the embedded demo drive (5.5 min without the venv's set-up, on a quiet 2-core VM:
# benchmarks/results/demo.md). `make test`: the test suite. Both set up first when needed.
VENV ?= .venv
STAMP := $(VENV)/.drivesim-installed
WORKSPACE ?= drivesim-work

.PHONY: install demo test lint bench clean

$(STAMP): pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh
	touch $@

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) run --preset demo

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

clean:
	rm -rf $(WORKSPACE) .pytest_cache
