PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DOCS_STAMP := $(VENV)/.docs-installed
LUMOS_STAMP := $(VENV)/.lumos-installed
# setuptools-scm takes the version from git or an sdist's PKG-INFO; a copy with neither (a
# source archive, or no git program) is installed as 0+unknown instead of failing to build.
HAS_VERSION := $(or $(wildcard PKG-INFO),$(and $(wildcard .git),$(shell command -v git)))
VERSION_ENV := $(if $(HAS_VERSION),,SETUPTOOLS_SCM_PRETEND_VERSION_FOR_SATSTREAK_INJECT=0+unknown)

.PHONY: install install-lumos test lint slow demo focalplane figures bench docs clean

$(BIN)/python:
	@echo "==> creating the virtual environment $(VENV) with $(PYTHON)"
	$(PYTHON) -m venv $(VENV)
	@echo "==> upgrading pip in $(VENV)"
	$(BIN)/python -m pip install --quiet --upgrade pip

# --group dev: pyproject's development tools (ruff, import-linter, mypy). It needs pip >= 25.1,
# which an older .venv may lack: pip is upgraded above only when .venv is made.
$(STAMP): $(BIN)/python pyproject.toml
	@echo "==> installing inject, its dependencies and the development tools into $(VENV) (GalSim,"
	@echo "    astropy, OpenCV, OpenImageIO, pytest, mypy...; a minute or two the first time, quiet meanwhile)"
	$(BIN)/python -m pip install --quiet 'pip>=25.1'
	$(VERSION_ENV) $(BIN)/python -m pip install --quiet -e '.[test]' --group dev
	@touch $(STAMP)
	@echo "==> installed: run .venv/bin/inject, or 'source .venv/bin/activate' and then inject"

install: $(STAMP)

# lumos-sat (optional BRDF brightness, inject/orbits/lumos.py) pins numpy 1.24, astropy 5.2 and
# scipy 1.10, older than inject needs, and opencv-python 4.7, a second cv2 beside inject's
# OpenCV: it goes in without its dependencies, and only on request, since no environment
# holding it passes pip check.
$(LUMOS_STAMP): $(STAMP)
	@echo "==> installing lumos-sat (optional BRDF brightness) with --no-deps: its pins (numpy 1.24,"
	@echo "    astropy 5.2, opencv-python 4.7) would replace inject's; pip check and later installs list them"
	$(BIN)/python -m pip install --quiet --no-deps 'lumos-sat==1.0.9'
	@touch $(LUMOS_STAMP)

install-lumos: $(LUMOS_STAMP)

# The tests run on up to 4 processes (pytest-xdist), one per CPU this job may use: with one
# CPU, in this process.
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ $$n -gt 4 ] && n=4; \
	[ $$n -lt 2 ] && n=0; echo $$n)

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS)

# pip check: every installed package's requirements met. Once lumos-sat is installed its own
# pins cannot be, so its lines are left out and any other line still fails.
lint: $(STAMP)
	@if $(BIN)/python -m pip show --quiet lumos-sat 2>/dev/null; then \
		echo "==> pip check, less lumos-sat's own pins (see make install-lumos)"; \
		! $(BIN)/python -m pip check | grep -v '^lumos-sat '; \
	else \
		echo "==> pip check"; \
		$(BIN)/python -m pip check; \
	fi
	$(BIN)/ruff check inject tests scripts
	$(BIN)/lint-imports
	$(BIN)/mypy

# The tests marked slow, then the property tests at their full count of examples (the default
# suite draws fewer of those that build a short track's tables at each angle).
slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow
	INJECT_TEST_EXAMPLES=12 $(BIN)/python -m pytest -q tests/test_properties.py

demo: $(STAMP)
	@mkdir -p out
	@echo "==> simulating sample_fields/default.yaml: one full ITL CCD with sky, stars, noise and"
	@echo "    the paper's satellite (about 10-30 s)"
	$(BIN)/inject simulate sample_fields/default.yaml -o out/default.fits --exr out/default.exr \
		--png out/default.png --truth out/default_truth.csv --overwrite
	@echo "outputs: out/default.fits (IMAGE MASK VARIANCE STREAK_MODEL TRUTH TRUTH_VERTICES), out/default.exr,"
	@echo "         out/default.png (quicklook), out/default_truth.csv, out/default_truth_vertices.csv"
	@echo "to run inject yourself: .venv/bin/inject --help, or: source .venv/bin/activate; inject --help"

focalplane: $(STAMP)
	@mkdir -p out
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

$(DOCS_STAMP): $(STAMP)
	@echo "==> installing the documentation tools (MkDocs, Material, mkdocstrings) into $(VENV)"
	$(VERSION_ENV) $(BIN)/python -m pip install --quiet -e '.[docs]'
	@touch $(DOCS_STAMP)

# The site goes to out/site; --strict turns every warning (a broken link, a missing page,
# an unreadable docstring) into an error.
docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true $(BIN)/mkdocs build --strict -d out/site
	@echo "docs: out/site/index.html"

clean:
	rm -rf $(VENV) out build *.egg-info
