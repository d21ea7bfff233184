"""rodsnes.collective.on_root: rank 0's result on every rank, its exception raised on every rank
(one that cannot be pickled as a RuntimeError naming it), on the ranks of mpirun."""
import pytest
from mpi4py import MPI

from rodsnes.collective import on_root
from rodsnes.errors import SceneError


class _Unpicklable(Exception):
    def __init__(self, message):
        super().__init__(message)
        self.hook = lambda: message         # a lambda: pickle refuses it


def _refuse():
    raise SceneError("-output_dir x: cannot be made", ("-output_dir",))


def _odd():
    raise _Unpicklable("odd")


@pytest.mark.mpi
def test_rank_0s_result_and_exceptions_reach_every_rank():
    comm = MPI.COMM_WORLD
    assert on_root(comm, lambda: ("rank", comm.rank)) == ("rank", 0)
    with pytest.raises(SceneError) as err:
        on_root(comm, _refuse)
    assert err.value.options == ("-output_dir",)
    with pytest.raises(_Unpicklable if comm.size == 1 else RuntimeError, match="odd"):
        on_root(comm, _odd)
    assert comm.allreduce(1) == comm.size           # every rank still meets the next one
