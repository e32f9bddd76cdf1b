"""RANSAC's minimal samples: ``sample_triples`` must give exactly what ``rng.choice(n, 3,
replace=False)`` called once per sample gives (it replaced that loop: a loop closure's and
a merge's verification must not change with it), and leave the generator where those calls
leave it."""

from __future__ import annotations

import numpy as np
import pytest

from fleetslam.backend.geometric_verification import sample_triples


def _by_choice(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    return np.array([rng.choice(n, 3, replace=False) for _ in range(count)],
                    np.int64).reshape(count, 3)


@pytest.mark.parametrize("n", [3, 4, 5, 17, 300, 12_345, 70_000, 2**31 + 5])
@pytest.mark.parametrize("half_used", [False, True])
def test_sample_triples_equals_rng_choice_and_leaves_the_same_generator(n, half_used):
    for seed in range(12):
        expected_rng, rng = np.random.default_rng(seed), np.random.default_rng(seed)
        if half_used:  # a 32-bit draw before leaves half of a 64-bit one for the next
            expected_rng.integers(0, 10)
            rng.integers(0, 10)
        count = 1 + seed * 13 % 300
        expected = _by_choice(expected_rng, n, count)
        got = sample_triples(rng, n, count)
        assert got.dtype == np.int64 and np.array_equal(got, expected), (n, seed)
        assert rng.bit_generator.state == expected_rng.bit_generator.state, (n, seed)
        assert np.array_equal(rng.integers(0, 1 << 30, 8), expected_rng.integers(0, 1 << 30, 8))


def test_sample_triples_of_another_bit_generator_are_rng_choice_s():
    expected_rng = np.random.Generator(np.random.MT19937(7))
    rng = np.random.Generator(np.random.MT19937(7))
    assert np.array_equal(sample_triples(rng, 50, 40), _by_choice(expected_rng, 50, 40))
    assert rng.bit_generator.state["state"]["pos"] == expected_rng.bit_generator.state["state"]["pos"]
