"""Thread caps: the small-work rule, the explicit request, and the cap that restores what it changed."""

import numba
import pytest
import torch

from seggaussian.util.threads import PARALLEL_MIN_GAUSSIANS, thread_cap, threads_for_gaussians


def test_small_work_gets_one_thread_large_work_keeps_the_current_count():
    assert threads_for_gaussians(0) == 1
    assert threads_for_gaussians(PARALLEL_MIN_GAUSSIANS - 1) == 1
    assert threads_for_gaussians(PARALLEL_MIN_GAUSSIANS) == torch.get_num_threads()


def test_an_explicit_request_wins_and_must_be_positive():
    assert threads_for_gaussians(10, requested=3) == 3
    assert threads_for_gaussians(10**9, requested=1) == 1
    with pytest.raises(ValueError, match="at least 1"):
        threads_for_gaussians(10, requested=0)


def test_thread_cap_sets_both_pools_and_restores_them_even_on_error():
    torch_before, numba_before = torch.get_num_threads(), numba.get_num_threads()
    with pytest.raises(RuntimeError):
        with thread_cap(1):
            assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
            raise RuntimeError("inside")
    assert (torch.get_num_threads(), numba.get_num_threads()) == (torch_before, numba_before)
