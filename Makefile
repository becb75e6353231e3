# `make demo`: the main job on the embedded demo drive; `make test`: the test suite. Both set up on first use.
VENV ?= .venv
STAMP := $(VENV)/.drivesim-installed
WORKSPACE ?= drivesim-work

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh
	touch $@

demo: $(STAMP)
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) synth --seed 0 --duration-s 8 --output $(WORKSPACE)/recordings/demo.mcap --preview
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) ingest $(WORKSPACE)/recordings/demo.mcap
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) preprocess
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) build-world
	$(VENV)/bin/drivesim --workspace $(WORKSPACE) status

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

clean:
	rm -rf $(WORKSPACE) .pytest_cache
