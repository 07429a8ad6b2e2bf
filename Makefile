# Two entry points: `make run` (daemon on the digital twin) and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test bench clean

# Under a lock, and only if still stale once the lock is held: two `make test` started at once on one machine would
# otherwise both build the same .venv/ and one would fail on the other's half-written files.
$(STAMP): pyproject.toml
	flock .venv.lock sh -c 'if [ ! $(STAMP) -nt pyproject.toml ]; then \
	  $(PYTHON) -m venv $(VENV) && $(BIN)/python -m pip install -q --upgrade pip && \
	  $(BIN)/python -m pip install -q -e ".[test]" && touch $(STAMP); fi'

run: $(STAMP)
	$(BIN)/drillnav serve --twin

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	for b in benchmarks/*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
