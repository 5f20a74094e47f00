"""`--threads` of eval, serve and train: a count, or auto (one thread for a small model, torch's default otherwise)."""

from __future__ import annotations

import argparse
import importlib

import pytest
import torch

from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.utils.threads import SMALL_MODEL_PARAMETERS, set_threads, threads_option


def test_auto_runs_a_small_model_on_one_thread_and_leaves_a_large_one_alone() -> None:
    before = torch.get_num_threads()
    small = PI0ForActionGeneration(PI0Config.from_preset("pi0_small"))
    large = torch.nn.Linear(SMALL_MODEL_PARAMETERS // 1000, 1000)  # just at the threshold
    try:
        torch.set_num_threads(2)
        assert set_threads(None, small) == 1 == torch.get_num_threads()
        torch.set_num_threads(2)
        assert set_threads(None, large) == 2 == torch.get_num_threads()
        assert set_threads(3, small) == 3 == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def test_the_option_takes_a_positive_count_or_auto() -> None:
    assert threads_option("auto") is None and threads_option("4") == 4
    for bad in ("0", "-1", "two", "1000000"):  # (`serve --threads 1000000` crashed torch's thread pool)
        with pytest.raises(argparse.ArgumentTypeError, match="expected a number of threads in \\[1, 1024\\] or auto"):
            threads_option(bad)


@pytest.mark.parametrize("module", ["pi0_torch.runtime.rollout", "pi0_torch.runtime.serving", "pi0_torch.training.trainer"])
def test_eval_serve_and_train_take_threads(module: str) -> None:
    parser = argparse.ArgumentParser()
    importlib.import_module(module).add_arguments(parser)
    action = next(a for a in parser._actions if "--threads" in a.option_strings)
    assert action.default is None and action.type is threads_option
