import pytest
import torch


@pytest.fixture(autouse=True)
def one_torch_thread():
    """The renderer tests work on small tensors: one intra-op thread is faster than two on a shared CI
    machine (OpenMP barriers spin when cores are oversubscribed) and makes runs reproducible."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
