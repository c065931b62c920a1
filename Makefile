PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install test slow demo focalplane figures bench clean

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
	@mkdir -p out
	$(BIN)/inject simulate sample_fields/default.yaml -o out/default.fits --exr out/default.exr \
		--png out/default.png --truth out/default_truth.csv --overwrite
	@echo "outputs: out/default.fits (IMAGE MASK VARIANCE STREAK_MODEL TRUTH), out/default.exr,"
	@echo "         out/default.png (quicklook), out/default_truth.csv"

focalplane: $(STAMP)
	$(BIN)/inject focalplane sample_fields/focal_paper_550km.yaml -o out/focalplane \
		--streak-ccds-only
	@echo "outputs: out/focalplane/R*_S*.fits (the CCDs the streak reaches), manifest.csv,"
	@echo "         mosaic.png (the whole focal plane; CCDs not rendered are outlined)"

figures: $(STAMP)
	$(BIN)/python scripts/paper_figures.py --out out/figures

bench: $(STAMP)
	$(BIN)/python scripts/bench_render.py --out out/bench
	$(BIN)/python scripts/bench_scene.py --repeat 3
	$(BIN)/python scripts/bench_mask.py --sections timing

clean:
	rm -rf $(VENV) out build *.egg-info
