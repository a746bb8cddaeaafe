"""The trajectory bookkeeping the CPU and Warp engines share (`simloader.trajectories`): the
same decisions in NumPy and in torch, and a checkpoint that restores bit for bit."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from simloader.trajectories import Trajectories


def _config(nbatch=5, continuing=True, models=None):
    return SimpleNamespace(nbatch=nbatch, continue_episodes=continuing, models=models)


def _both(config):
    return Trajectories(config), Trajectories(config, torch.device("cpu"))


def _drawn(rng, n):
    return {"variant": rng.integers(0, 3, n), "mass": rng.uniform(size=(n, 2))}


@pytest.mark.parametrize("continuing", [True, False])
def test_fresh_rows_take_new_draws_and_the_others_keep_theirs(continuing):
    rng = np.random.default_rng(0)
    host, device = _both(_config(continuing=continuing))
    first, second = _drawn(rng, 5), _drawn(rng, 5)
    diverged = np.array([True, False, False, True, False])
    for t, convert in ((host, np.asarray), (device, torch.as_tensor)):
        t.take({k: convert(v) for k, v in first.items()})  # every row fresh at first
        t.finished(convert(diverged))
        t.take({k: convert(v) for k, v in second.items()})
    rows = diverged if continuing else np.ones(5, bool)
    for key in first:
        want = np.where(rows.reshape(-1, *[1] * (first[key].ndim - 1)), second[key], first[key])
        np.testing.assert_array_equal(host.params[key], want)
        np.testing.assert_array_equal(device.params[key].numpy(), want)
    np.testing.assert_array_equal(host.model_index, host.params["variant"])
    table = np.arange(3 * 4.0).reshape(3, 4)  # one row per variant
    np.testing.assert_array_equal(host.per_trajectory(table), table[host.params["variant"]])
    np.testing.assert_array_equal(device.per_trajectory(torch.as_tensor(table)).numpy(),
                                  table[host.params["variant"]])


def test_one_model_tables_broadcast_and_model_lists_index_by_trajectory():
    host, device = _both(_config(models=[object()] * 5))
    table = np.arange(5 * 2.0).reshape(5, 2)
    np.testing.assert_array_equal(host.per_trajectory(table), table)
    np.testing.assert_array_equal(device.per_trajectory(torch.as_tensor(table)).numpy(), table)
    one = Trajectories(_config())
    assert one.per_trajectory(np.ones((1, 3))).shape == (5, 3)


def test_a_checkpoint_restores_bit_for_bit_across_array_libraries():
    rng = np.random.default_rng(1)
    host, device = _both(_config())
    host.take(_drawn(rng, 5))
    rows = rng.standard_normal((5, 7))
    fresh = np.array([False, True, False, False, True])
    saved = host.checkpoint(rows, fresh, host.params)
    restored = device.restore(saved)
    assert torch.equal(restored, torch.as_tensor(rows))
    np.testing.assert_array_equal(device.fresh.numpy(), fresh)
    for key, value in host.params.items():
        np.testing.assert_array_equal(device.params[key].numpy(), value)
    np.testing.assert_array_equal(device.model_index.numpy(), host.params["variant"])
    again = Trajectories(_config()).restore(device.checkpoint(restored, device.fresh,
                                                              device.params))
    np.testing.assert_array_equal(again, rows)
