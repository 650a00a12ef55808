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

# Until the controllers exist (issue 4) the demo prints the serial arms' model at the thesis's
# joint-space initial configuration of arm 1 and arm 2.
demo: $(STAMP)
	$(BIN)/cochlea-model serial --arm arm1 --at-deg 73 83 110
	$(BIN)/cochlea-model serial --arm arm2 --at-deg 110 -128 100

test: $(STAMP)
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
