# Set-up and entry points. `make demo` and `make test` install whatever is missing on a fresh
# Debian bookworm machine (as root, or with sudo), then run.
SHELL := /bin/bash
PY := /usr/bin/python3
VENV := .venv
VPY := $(VENV)/bin/python
NP ?= 2
APT_PACKAGES := python3-dolfinx-real python3-ufl python3-petsc4py python3-mpi4py python3-numpy \
	python3-meshio python3-h5py python3-scipy python3-matplotlib python3-pytest python3-venv \
	python3-setuptools python3-tqdm python3-hypothesis python3-cffi python3-pytest-xdist \
	openmpi-bin libopenblas0-pthread
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

# OpenMPI refuses to run as root without these; CI runs as root.
export OMPI_ALLOW_RUN_AS_ROOT := 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM := 1
export OMPI_MCA_rmaps_base_oversubscribe := 1
export DEBIAN_FRONTEND := noninteractive

.PHONY: install system-packages demo test test-serial test-mpi test-all clean

system-packages:
	@missing=""; for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq < /dev/null && \
	  $(SUDO) apt-get install -y -qq $$missing < /dev/null; \
	fi

$(VENV)/.installed: pyproject.toml | system-packages
	$(PY) -m venv --system-site-packages $(VENV)
	$(VPY) -m pip install --quiet --no-build-isolation --no-index -e .
	$(VPY) -m compileall -q fem_dual > /dev/null  # (bytecode, where the environment writes none)
	touch $@

# The compiled loops, built into the package with the compiler the FFCx JIT uses (without one,
# the numpy loops run; a library older than its sources is compiled again at run time).
NATIVE_LIB := fem_dual/native/_lib/libfem_dual_native.so
$(NATIVE_LIB): $(VENV)/.installed $(wildcard fem_dual/native/src/*.c fem_dual/native/src/*.h)
	$(VPY) -m fem_dual.native.build

install: system-packages $(VENV)/.installed $(NATIVE_LIB)

demo: install
	$(VPY) demos/demo_ziegler.py

# The serial tests on two workers (pytest-xdist; one per core), then the MPI tests under mpirun.
# `make test-all` adds the long cases (marked slow): run it before every release.
SLOW ?=
# One BLAS thread per test process: two workers (or two ranks) already fill the two cores.
test-serial: install
	OPENBLAS_NUM_THREADS=1 $(VPY) -m pytest -q --color=no -n $(NP) $(SLOW) tests

test-mpi: install
	OPENBLAS_NUM_THREADS=1 mpirun -n $(NP) $(VPY) -m pytest -q --color=no -m mpi $(SLOW) tests

test: test-serial test-mpi

test-all:
	$(MAKE) test SLOW=--slow

clean:
	rm -rf $(VENV) out_* build *.egg-info fem_dual/native/_lib
