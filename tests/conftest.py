import gc
import os

import pytest

os.environ.setdefault("OMPI_ALLOW_RUN_AS_ROOT", "1")
os.environ.setdefault("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
if os.environ.get("OMPI_MCA_ess") == "singleton":
    # a pytest-xdist worker, started by a controller that had MPI initialised on its own: the
    # singleton's variables would make every mpirun the tests start fail without a word (and
    # this process's own MPI join the controller's); each process starts MPI afresh
    for _name in [k for k in os.environ if k.startswith(("PMIX_", "OMPI_MCA_", "OMPI_APP_"))
                  and k != "OMPI_MCA_rmaps_base_oversubscribe"]:
        del os.environ[_name]

from mpi4py import MPI  # noqa: E402 -- after the environment is clean


@pytest.fixture(autouse=True)
def _collective_teardown():
    yield
    gc.collect()
    MPI.COMM_WORLD.barrier()


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true", help="also run the tests marked slow")


def pytest_collection_modifyitems(config, items):
    """Under mpirun, skip what is only meaningful on one rank; skip slow tests unless --slow."""
    if not config.getoption("--slow"):
        skip_slow = pytest.mark.skip(reason="slow: run with pytest --slow")
        for item in items:
            if "slow" in item.keywords:
                item.add_marker(skip_slow)
    if MPI.COMM_WORLD.size > 1:
        skip = pytest.mark.skip(reason="serial-only test")
        for item in items:
            if "serial" in item.keywords:
                item.add_marker(skip)
