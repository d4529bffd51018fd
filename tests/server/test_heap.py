"""server.heap: a served step's large arrays kept warm between steps."""

import platform

import numpy as np
import pytest

from server.heap import keep_freed_memory


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_glibc_keeps_freed_memory_and_arrays_still_work():
    assert keep_freed_memory() is True
    # A step's worth of megabyte arrays, allocated and freed again and again, as a server does.
    for size in (300, 310, 290):
        system = np.zeros((size, size))
        system.flat[::size + 1] = 1.0
        assert np.linalg.solve(system, np.ones(size)).sum() == size
