# workcell: two commands do everything on a fresh clone: `make demo` and `make test`.
VENV    ?= .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
PYTHON  ?= python3
export JAX_PLATFORMS ?= cpu
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
# pytest-xdist workers for `make test` (one per core on CI's 2-core machine; each test file runs
# whole in one worker, so its module fixtures are built once; TEST_WORKERS=0 runs in-process)
TEST_WORKERS ?= 2
PYTEST_PAR := -n $(TEST_WORKERS) --dist loadfile

.PHONY: install demo test test-all fuzz bench lint format clean

install: $(STAMP)

ifneq ($(words $(VENV)),1)
$(error VENV must be a path without spaces (make cannot name a target with one), got "$(VENV)")
endif

# a venv left without pip (an interrupted first run, a Python without ensurepip) is made again;
# --clear only for a folder that is a venv (VENV=some/other/folder is never emptied)
$(STAMP): pyproject.toml
	$(PY) -m pip --version >/dev/null 2>&1 || \
	  if [ -f $(VENV)/pyvenv.cfg ]; then $(PYTHON) -m venv --clear $(VENV); \
	  else $(PYTHON) -m venv $(VENV); fi
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: install
	$(VENV)/bin/workcell demo

test: install
	$(PY) -m pytest -q -m "not slow" $(PYTEST_PAR)

test-all: install
	$(PY) -m pytest -q $(PYTEST_PAR)

# property tests with fresh random examples, FUZZ_RUNS times (`make test` draws fixed ones)
FUZZ_RUNS ?= 5
fuzz: install
	for i in $$(seq $(FUZZ_RUNS)); do \
	  HYPOTHESIS_PROFILE=fuzz $(PY) -m pytest -q -m "not slow" -p no:cacheprovider \
	    $$(grep -l "@given" tests/*.py) || exit 1; \
	done

bench: install
	$(VENV)/bin/workcell bench all

lint: install
	$(VENV)/bin/ruff check workcell sim_devices tests
	$(VENV)/bin/ruff format --check workcell sim_devices tests

format: install
	$(VENV)/bin/ruff format workcell sim_devices tests
	$(VENV)/bin/ruff check --fix workcell sim_devices tests

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
