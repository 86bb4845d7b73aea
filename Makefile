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

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -m "not packaging and not flight and not measurement"

clean:
	rm -rf $(VENV) build *.egg-info
