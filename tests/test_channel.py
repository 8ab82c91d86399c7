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


def test_arrays_of_every_kind_round_trip_bit_for_bit_and_writable(server):
    """The channel's own reduction of plain arrays, and NumPy's for the rest: same dtype,
    shape, order and bits (NaN payloads and -0.0 included), writable where they were."""
    rng = np.random.default_rng(1)
    plain = rng.standard_normal((3, 4))
    plain[0, 0], plain[0, 1] = -0.0, np.float64(np.nan)
    arrays = [
        plain, plain.astype(">f8"), plain.astype(np.float32), np.arange(5, dtype=np.int8),
        np.array([True, False]), (plain + 1j * plain).astype(np.complex128),
        np.array(["2026-12-07", "NaT"], dtype="datetime64[s]"), np.zeros((0, 3)),
        np.full((), 2.5), np.asfortranarray(plain), plain[:, ::2],
        np.array([(1, 2.0)], dtype=[("a", "i4"), ("b", "f8")]),
        np.array([{"x": 1}, None], dtype=object),
    ]
    channel = Channel(server.address)
    channel.send(list, ["odd", *arrays])  # a pickle stream of any length before the buffers
    _, *back = channel.receive(5.0)
    channel.close()
    for sent, got in zip(arrays, back, strict=True):
        assert got.dtype == sent.dtype and got.shape == sent.shape
        assert got.flags.f_contiguous == sent.flags.f_contiguous
        assert got.flags.writeable and got.flags.aligned
        if sent.dtype.hasobject:
            assert got.tolist() == sent.tolist()
        else:
            assert np.ascontiguousarray(got).tobytes() == np.ascontiguousarray(sent).tobytes()


def test_received_arrays_are_aligned_so_their_sums_are_a_fresh_arrays(server):
    """An unaligned float64 array sums in another order (NumPy buffers it): the channel's
    arrays must give a fresh array's sum bit for bit, whatever precedes them."""
    values = np.random.default_rng(2).standard_normal(10_000) * 1e5
    channel = Channel(server.address)
    for prefix in range(1, 24):
        channel.send(list, ["x" * prefix, values, values[1:].copy()])
        _, first, second = channel.receive(5.0)
        assert first.sum() == values.sum() and second.sum() == values[1:].sum()
    channel.close()
