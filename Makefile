# Two commands on a fresh machine with Python 3.11: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The versions the Dockerfile installs too (see its top and `make lock`): host and cluster run the same Dask.
CONSTRAINTS := constraints.txt

.PHONY: demo test bench lock clean

$(STAMP): pyproject.toml $(CONSTRAINTS)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# torch first, at the pinned version, from the configured package index: this project's index serves the
	# CPU build; from plain PyPI on Linux the same line pulls the CUDA build (gigabytes) - there, add
	# --index-url https://download.pytorch.org/whl/cpu for the CPU one (README, Install).
	$(BIN)/pip install --quiet -c $(CONSTRAINTS) torch==2.13.0
	$(BIN)/pip install --quiet -c $(CONSTRAINTS) -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/cscsr demo --out demo-output

# Three pytest processes (pytest-xdist), a test file each at a time: most tests wait on clusters, processes and
# signals, so three of them share 2 cores well, 16 % sooner than two (docs/reliability.md, A suite for any machine).
test: $(STAMP)
	$(BIN)/python -m pytest -q -rfE --durations=30 --numprocesses 3 --dist loadfile

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

# Rewrite constraints.txt from what .venv holds (after changing a dependency): every package but
# the project itself; torch without its local label (+cpu), so the CPU and the CUDA wheels both match.
lock: $(STAMP)
	{ sed -n '/^#/p' $(CONSTRAINTS); $(BIN)/pip freeze --exclude-editable \
	    | sed -E '/^#/d; s/^(torch==[^+]*)\+.*/\1/'; } > $(CONSTRAINTS).new
	mv $(CONSTRAINTS).new $(CONSTRAINTS)

clean:
	rm -rf $(VENV) demo-output benchmarks/results
