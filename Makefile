# bsipipe: `make study` reruns the sample study, `make test` runs the tests, `make bench` the benchmarks.
# Each target installs what it needs into .venv on a fresh machine (only Python required).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install study test bench ccx clean

$(STAMP): pyproject.toml setup.py bsipipe/imaging/_kernels.c
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test,bench,workflow]'
	touch $(STAMP)

install: $(STAMP)

# CalculiX checks the emitted ABAQUS cards; tests skip with a reason where it cannot be installed.
ccx:
	@command -v ccx >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update -qq && apt-get install -y -qq calculix-ccx) >/dev/null 2>&1 || echo "note: calculix-ccx could not be installed; solver checks will skip"; \
	  else echo "note: no root/apt-get; CalculiX solver checks will skip"; fi; }

study: $(STAMP) ccx
	$(BIN)/bsipipe study configs/study.yaml

test: $(STAMP) ccx
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2

# SIGKILL `bsipipe study` of the sample study at 20 random moments, rerun, and compare with a clean run
# (issue 7); runs in a scratch folder (not results/), about 20 clean-study times.
.PHONY: kill-trials
kill-trials: $(STAMP) ccx
	$(BIN)/python scripts/kill_rerun_trials.py --config configs/study.yaml --trials 20

bench: $(STAMP)
	$(BIN)/python bench/run.py

clean:
	rm -rf results .pytest_cache
