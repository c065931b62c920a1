PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install test slow demo figures clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

demo: $(STAMP)
	$(BIN)/inject profile --height 550 --zenith 70 --length 7.25 --width 2.65 --mag 5 --band g
	$(BIN)/inject profile --height 350 --zenith 70 --length 7.25 --width 2.65 --mag 5 --band g

figures: $(STAMP)
	$(BIN)/python scripts/paper_figures.py --out out/figures

clean:
	rm -rf $(VENV) out build *.egg-info
