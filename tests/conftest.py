"""Shared pytest fixtures."""

import random

import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True)
def seeded_random_state():
    """Seed the global torch, numpy and Python generators before every test.

    Tests that draw unseeded random inputs (``torch.rand(...)``) then see the same inputs on every
    run and machine, so a pass or a failure is reproducible rather than a draw.
    """
    torch.manual_seed(1234)
    np.random.seed(1234)
    random.seed(1234)


@pytest.fixture(scope="module")
def single_thread():
    """Run a module's tiny-tensor tests with one torch thread.

    On a loaded 2-core machine torch's 2-thread OpenMP costs up to 50x on tiny tensors.
    Use with ``pytestmark = pytest.mark.usefixtures("single_thread")``.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
