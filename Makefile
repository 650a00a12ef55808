# cochlea: the two commands a new machine needs are `make demo` and `make test`.
# Both create the virtual environment (.venv) and install the package on first use.

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test install clean

# The stamp is rebuilt when the package's metadata changes.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

# The main job: the thesis's task-space study of the serial system (controller g) on the
# simulated robot; the log, summary.json and figures land in runs/demo/.
demo: $(STAMP)
	$(BIN)/cochlea-run --robot serial --space task --out runs/demo

test: $(STAMP)
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
