"""The coordinator–worker socket channel (``ocpar.bsp.channel``) on its own, without Dask."""

from __future__ import annotations

import numpy as np
import pytest

from ocpar.bsp.channel import SOLVE_LOCK, Channel, ChannelServer


def lock_is_held() -> bool:
    return SOLVE_LOCK.locked()


@pytest.fixture
def server():
    server = ChannelServer("127.0.0.1")
    yield server
    server.close()


def test_large_arrays_round_trip_exactly(server):
    # 16 MB in out-of-band frames
    arrays = {"a": np.random.default_rng(0).standard_normal(2_000_000), "b": np.arange(7)}
    channel = Channel(server.address)
    channel.send(dict, arrays)
    back = channel.receive(30.0)
    channel.close()
    assert back.keys() == arrays.keys()
    for key, value in arrays.items():
        np.testing.assert_array_equal(back[key], value)


def test_requests_run_under_the_solve_lock_and_errors_reach_the_caller(server):
    channel = Channel(server.address)
    channel.send(lock_is_held)
    assert channel.receive(5.0) is True
    channel.send(int, "not a number")
    with pytest.raises(ValueError, match="not a number"):
        channel.receive(5.0)
    channel.send(sum, [1, 2, 3])  # the channel is still in step after an error
    assert channel.receive(5.0) == 6
    channel.close()


def test_two_coordinators_are_answered_one_request_at_a_time(server):
    channels = [Channel(server.address) for _ in range(2)]
    for c in channels:
        c.send(lock_is_held)
    assert [c.receive(5.0) for c in channels] == [True, True]
    for c in channels:
        c.close()
