"""Every solver test runs over both implementations of the block-sparse loops: the compiled
kernels (:mod:`fieldcal.solver.blocksparse_kernels`) and the NumPy reference."""

import pytest

from fieldcal.solver import blocksparse_kernels


@pytest.fixture(params=["compiled", "numpy"], autouse=True)
def loops(request, monkeypatch):
    if request.param == "numpy":
        for name in blocksparse_kernels.__all__:
            monkeypatch.setattr(blocksparse_kernels, name, lambda: None)
    elif blocksparse_kernels.assemble() is None:
        pytest.skip("the compiled kernels are not available here")
    return request.param
