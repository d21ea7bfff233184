# Everything a fresh Debian bookworm machine needs: `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
SYS_PYTHON := /usr/bin/python3
NP ?= 2
CASE ?= cases/mattiasson.opts
MPIRUN := mpirun -n $(NP) --bind-to none
export OMPI_ALLOW_RUN_AS_ROOT := 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM := 1
export OMPI_MCA_btl := self,vader
export OMPI_MCA_rmaps_base_oversubscribe := 1
export OMP_NUM_THREADS := 1
# an MPI rank waiting for a message yields its core instead of spinning: on a 2-core box shared
# with other work the spinning ranks of `mpirun -n 2` starved each other (test-mpi: 4 s instead
# of 14-87 s for the same 5 tests, measured back to back)
export OMPI_MCA_mpi_yield_when_idle := 1
PYTEST := $(PY) -m pytest -q -p no:cacheprovider --color=no
# slow tests (> ~5 s) not yet marked @pytest.mark.slow in their files: make test-fast leaves
# them out too (prefixes of test ids; drop a line once its test carries the mark)
.PHONY: install demo test test-fast test-serial test-mpi bench clean

install: $(VENV)/.installed

# every compiled kernel's source and header (setup.py's KERNELS): an edited kernel is rebuilt
$(VENV)/.installed: setup.py tools/install_system.sh $(wildcard rodsnes/*/_*.c rodsnes/*/_*.h)
	tools/install_system.sh
	test -x $(PY) || $(SYS_PYTHON) -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e .
	touch $@

demo: install
	$(MPIRUN) $(VENV)/bin/rodsnes -options_file $(CASE)

# everything: every test serially (NP workers), then the collective ones (marked mpi) on NP ranks
test: install
	$(PYTEST) -n $(NP) --dist loadfile tests
	$(MPIRUN) tools/mpi_rank0_output.sh $(PYTEST) -m mpi tests

# after every edit (under a minute): unit, tangent-against-differences, kernel and scene tests,
# the collective ones serially; no test marked slow
test-fast: install
	$(PYTEST) -n $(NP) --dist loadfile -m "not slow" tests

test-serial: install
	$(PYTEST) -n $(NP) --dist loadfile tests

test-mpi: install
	$(MPIRUN) tools/mpi_rank0_output.sh $(PYTEST) -m mpi tests

clean:
	rm -rf out .pytest_cache
