# deepcontact: two commands set everything up.
#   make test   build what is missing (.venv, pinned deps, patched Box2D), run the tests
#   make demo   the main job
# Later runs skip what is already built: each step leaves a stamp keyed by its inputs.

PYTHON    ?= python3.11
VENV      := .venv
VPY       := $(VENV)/bin/python
DEPS      := $(VENV)/.deps-stamp
# The patched wheel is cached per (patch, build script): a changed patch rebuilds it.
BOX2D_KEY := $(shell cat box2d/deepcontact.patch box2d/build.sh | sha256sum | cut -c1-16)
BOX2D_DIR := .cache/box2d/$(BOX2D_KEY)
BOX2D_WHL := $(BOX2D_DIR)/.built
BOX2D     := $(VENV)/.box2d-$(BOX2D_KEY)

.PHONY: all setup box2d proto test demo default-model bench-engine clean distclean help
.DELETE_ON_ERROR:

all: setup

help:
	@echo "make test          set up on first use, then run the test suite"
	@echo "make demo          set up on first use, then run the main job"
	@echo "make default-model data, training and export of the default and the thesis's models (DEFAULT_ONLY=1, the default alone: about 6 h 30 min on 2 cores: its graph model 1 h 59 min with AVX-512 on 2026-11-30, 2 h 17 min with AVX2 before train-graph traced its step once, its classifier about 3 h 50 min more, the zoo's data and classifier about 20 min; GRID_ONLY=1, the grid models alone: 57 min on 2 AVX2 cores; docs/models.md)"
	@echo "make box2d         build and install the patched pybox2d only"
	@echo "make proto         regenerate the gRPC stubs from proto/ (committed; a test checks them)"
	@echo "make bench-engine  engine benchmark -> bench/results/engine.json"
	@echo "make clean         remove caches of tests and builds (keeps .venv)"
	@echo "make distclean     also remove .venv, the Box2D wheel cache and the compiled kernels"

$(VPY):
	$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "deepcontact needs Python 3.11 (set PYTHON=...)"'
	$(PYTHON) -m venv $(VENV)

# The editable install also compiles deepcontact/_transfer.c and _kinematics.c (setup.py) in place.
$(DEPS): requirements.lock pyproject.toml setup.py deepcontact/_transfer.c deepcontact/_kinematics.c \
         deepcontact/_admission.c deepcontact/_faces.c deepcontact/_route.c $(wildcard deepcontact/*.h) | $(VPY)
	$(VPY) -m pip install --quiet --disable-pip-version-check -r requirements.lock
	$(VPY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $@

$(BOX2D_WHL): box2d/deepcontact.patch box2d/build.sh | $(DEPS)
	PYTHON=$(VPY) bash box2d/build.sh $(BOX2D_DIR)
	touch $@

$(BOX2D): $(BOX2D_WHL)
	$(VPY) -m pip install --quiet --disable-pip-version-check --no-deps --force-reinstall $(BOX2D_DIR)/*.whl
	rm -f $(VENV)/.box2d-*
	touch $@

box2d: $(BOX2D)

proto: $(DEPS)
	$(VPY) -m deepcontact.protogen

setup: $(DEPS) $(BOX2D)

test: setup
	$(VPY) -m pytest

demo: setup
	$(VENV)/bin/deepcontact demo

default-model: setup
	bash training/make_default_model.sh

bench-engine: setup
	$(VENV)/bin/deepcontact bench engine --json bench/results/engine.json

clean:
	rm -rf .pytest_cache build *.egg-info
	find . -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV) .cache deepcontact/*.so
