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

.PHONY: install demo test test-serial test-mpi bench clean

install: $(VENV)/.installed

$(VENV)/.installed: setup.py tools/install_system.sh rodsnes/_elastic_kernel.c
	tools/install_system.sh
	test -x $(PY) || $(SYS_PYTHON) -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e .
	touch $@

demo: install
	$(MPIRUN) $(VENV)/bin/rodsnes -options_file $(CASE)

test: install
	$(PY) -m pytest -q -p no:cacheprovider --color=no -n $(NP) --dist loadfile tests
	$(MPIRUN) tools/mpi_rank0_output.sh $(PY) -m pytest -q -p no:cacheprovider --color=no -m mpi tests

test-serial: install
	$(PY) -m pytest -q -p no:cacheprovider --color=no -n $(NP) --dist loadfile tests

test-mpi: install
	$(MPIRUN) tools/mpi_rank0_output.sh $(PY) -m pytest -q -p no:cacheprovider --color=no -m mpi tests

clean:
	rm -rf out .pytest_cache
