# The two commands of the README. Each makes its own virtual environment and installs everything into it.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,cluster]'
	touch $@

demo: $(BIN)/.installed
	$(BIN)/auxgps demo

# The tests that keep no clock run on every core (a file to a worker, so a module's fixture is built once); then the
# ones that run against the wall clock (flights on the emulator, a live camera) run alone, as a vehicle would.
NOT_CI_ONLY := not packaging and not flight and not measurement
test: $(BIN)/.installed
	status=0; \
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m "not realtime and $(NOT_CI_ONLY)" || status=$$?; \
	$(BIN)/python -m pytest -q -m "realtime and $(NOT_CI_ONLY)" || status=$$?; \
	exit $$status

clean:
	rm -rf $(VENV) build *.egg-info
