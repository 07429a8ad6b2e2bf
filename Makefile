# Two entry points: `make run` (daemon on the digital twin) and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test bench clean

# Under a lock, and only if still stale once the lock is held: two `make test` started at once on one machine would
# otherwise both build the same .venv/ and one would fail on the other's half-written files.
# The versions installed are those of .ci/constraints.txt: the ones the suite last passed on.
$(STAMP): pyproject.toml .ci/constraints.txt
	flock .venv.lock sh -c 'if [ ! $(STAMP) -nt pyproject.toml ] || [ ! $(STAMP) -nt .ci/constraints.txt ]; then \
	  $(PYTHON) -m venv $(VENV) && $(BIN)/python -m pip install -q --upgrade pip && \
	  $(BIN)/python -m pip install -q -c .ci/constraints.txt -e ".[test]" && touch $(STAMP); fi'

run: $(STAMP)
	$(BIN)/drillnav serve --twin

# Pure computation on every core (at most 4 workers, a module per worker), then the rest in one process: servers,
# daemons, browsers and every wall-clock bound they state (tests/conftest.py COMPUTE_MODULES). Both run; either failing fails.
test: $(STAMP)
	$(BIN)/python -m pytest -q -m compute -n auto --maxprocesses 4 --dist loadfile; a=$$?; \
	$(BIN)/python -m pytest -q -m "not compute"; b=$$?; \
	[ $$a -eq 0 ] && [ $$b -eq 0 ]

bench: $(STAMP)
	for b in benchmarks/*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
