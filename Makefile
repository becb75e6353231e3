# `make demo`: the main job, `drivesim run` on the embedded demo drive (about 10 min on 2 cores, venv set-up included); `make test`: the test suite. Both set up on first use.
VENV ?= .venv
STAMP := $(VENV)/.drivesim-installed
WORKSPACE ?= drivesim-work

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh
	touch $@

demo: $(STAMP)
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) run --preset demo

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

clean:
	rm -rf $(WORKSPACE) .pytest_cache
