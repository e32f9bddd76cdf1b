"""The map's arrays as a log (cloud/session/array_log.py): every chain restores the arrays bit
for bit, a patch carries exactly the rows that changed, a new base retires the old chain
only once it is on disk, and a damaged chain is refused before anything is allocated."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fleetslam.cloud.session import array_log
from fleetslam.cloud.session.array_log import ArrayLog, ArrayPatch, restore
from fleetslam.wire.data_tree import CheckpointError

NAMES = ("xyz", "count", "alive", "desc")


@dataclasses.dataclass
class Thing:
    xyz: np.ndarray
    count: np.ndarray
    alive: np.ndarray
    desc: np.ndarray
    label: str = "kept whole"


def _thing(rng: np.random.Generator, n: int) -> Thing:
    return Thing(rng.normal(size=(n, 3)), rng.integers(0, 9, n), rng.random(n) < 0.5,
                 rng.integers(0, 256, (n, 32), dtype=np.uint8))


def _same(a: Thing, arrays: dict[str, np.ndarray]) -> bool:
    return all(getattr(a, k).dtype == arrays[k].dtype and getattr(a, k).shape ==
               arrays[k].shape and getattr(a, k).tobytes() == arrays[k].tobytes()
               for k in NAMES)


def _edit(rng: np.random.Generator, t: Thing) -> None:
    """What a map's tracking and mapping do to its arrays: rows appended, rows changed,
    rows removed (observations compacted), bits a float compare would miss."""
    step = rng.integers(4)
    if step == 0:
        more = _thing(rng, int(rng.integers(1, 20)))
        for k in NAMES:
            setattr(t, k, np.concatenate([getattr(t, k), getattr(more, k)]))
    elif step == 1 and len(t.count):
        rows = rng.integers(0, len(t.count), 5)
        t.count[rows] += 1
        t.xyz[rows[:2]] = np.nan
        t.xyz[rows[2:3]] = -0.0  # equal to 0.0 as a float, not as bits
    elif step == 2 and len(t.count) > 3:
        keep = rng.random(len(t.count)) > 0.2
        for k in NAMES:
            setattr(t, k, getattr(t, k)[keep])
    else:
        t.alive = ~t.alive


def test_every_chain_restores_the_arrays_bit_for_bit(monkeypatch):
    monkeypatch.setattr(array_log, "MAX_PATCHES", 7)
    rng = np.random.default_rng(0)
    thing, log = _thing(rng, 30), ArrayLog(NAMES)
    bases = set()
    for _ in range(60):
        _edit(rng, thing)
        logged = log.logged(thing)
        assert not any(hasattr(logged.rest, k) for k in NAMES)
        assert logged.rest.label == "kept whole" and thing.xyz is not None  # the live one kept
        assert len(logged.arrays.patches) <= 7
        bases.add(id(logged.arrays.base))
        assert _same(thing, restore(logged.arrays, "here", 1 << 30))
    assert len(bases) > 2  # the chain started afresh along the way, and restored the same


def test_a_patch_carries_exactly_the_rows_that_changed():
    rng = np.random.default_rng(1)
    thing, log = _thing(rng, 1000), ArrayLog(NAMES)
    first = log.logged(thing).arrays
    assert log.logged(thing).arrays.patches == []  # nothing changed: no patch
    thing.count[[3, 500]] += 1
    thing.xyz[7, 2] = 0.5
    patch = log.logged(thing).arrays.patches[-1]
    assert set(patch.lengths) == {"count", "xyz"}
    assert patch.index["count"].tolist() == [3, 500] and patch.index["xyz"].tolist() == [7]
    assert patch.rows["xyz"].tolist() == [thing.xyz[7].tolist()]
    thing.count = np.concatenate([thing.count, [4, 5]])
    patch = log.logged(thing).arrays.patches[-1]
    assert patch.lengths == {"count": 1002} and patch.index["count"].tolist() == [1000, 1001]
    assert log.logged(thing).arrays.base is first.base
    # Bits, not float equality: a NaN left as it was is no change, 0.0 to -0.0 is one.
    thing.xyz[9, 1], thing.xyz[11, 0] = 0.0, np.nan
    patches = len(log.logged(thing).arrays.patches)
    assert len(log.logged(thing).arrays.patches) == patches
    thing.xyz[9, 1] = -0.0
    patch = log.logged(thing).arrays.patches[-1]
    assert set(patch.index) == {"xyz"} and patch.index["xyz"].tolist() == [9]


def test_a_replaced_chain_is_deleted_only_once_the_next_base_is_written(monkeypatch):
    monkeypatch.setattr(array_log, "MAX_PATCHES", 2)
    rng = np.random.default_rng(2)
    thing, log = _thing(rng, 50), ArrayLog(NAMES)
    chain = log.logged(thing).arrays
    old = [log.name_of(chain.base)]
    assert log.written(old) == []  # the first base replaced nothing
    for i in range(2):
        thing.count[i] += 1
        chain = log.logged(thing).arrays
        old.append(log.name_of(chain.patches[-1]))
    thing.count[5] += 1
    new = log.logged(thing).arrays
    assert new.patches == [] and new.base is not chain.base
    new_base = log.name_of(new.base)
    assert log.name_of(chain.base) is None  # no longer of the chain
    assert log.written(old) == []  # a checkpoint of the old chain: nothing to delete yet
    # The new base on disk: the old chain stays for readers of the checkpoint before.
    assert log.written([new_base, "f0000001-0123456789abcdef"]) == []
    for _ in range(3):  # the next base
        thing.count[7] += 1
        newer = log.logged(thing).arrays
    assert newer.patches == [] and newer.base is not new.base
    assert log.written([log.name_of(newer.base)]) == old
    assert log.written([log.name_of(newer.base)]) == []  # said once


def _patch(base_rows: int = 10, **change) -> tuple[dict, array_log.LoggedArrays]:
    base = array_log.ArrayBase("t", 1, {"count": np.arange(base_rows)})
    fields = {"lengths": {"count": base_rows + 1}, "index": {"count": np.array([2, base_rows])},
              "rows": {"count": np.array([7, 8])}}
    for key, value in change.items():
        fields[key] = {"count": value} if key != "names" else value
    if "names" in change:
        fields = {k: {change["names"]: v["count"]} for k, v in fields.items() if k != "names"}
    return fields, array_log.LoggedArrays(base, [ArrayPatch("t", 2, **fields)])


def test_a_sound_patch_restores():
    _, chain = _patch()
    assert restore(chain, "ckpt", 1 << 20)["count"].tolist() == [0, 1, 7, 3, 4, 5, 6, 7, 8,
                                                                   9, 8]


@pytest.mark.parametrize("change, why", [
    ({"index": np.array([2, 11])}, "not ascending inside its length 11"),
    ({"index": np.array([10, 2])}, "not ascending"),
    ({"index": np.array([-1, 10])}, "not ascending"),
    ({"index": np.array([2, 3]), "rows": np.array([7, 8])}, "grows by rows it does not give"),
    ({"rows": np.array([7.0, 8.0])}, "rows are not rows of it"),
    ({"rows": np.array([7])}, "rows are not rows of it"),
    ({"index": np.array([2.0, 10.0])}, "rows are not rows of it"),
    ({"lengths": 10 ** 15}, "of a length that is not one"),
    ({"lengths": -1}, "of a length that is not one"),
    ({"lengths": True}, "of a length that is not one"),
    ({"names": "other"}, "names other arrays than its base"),
])
def test_a_damaged_patch_is_refused_naming_the_file_before_allocating(change, why):
    _, chain = _patch(**change)
    with pytest.raises(CheckpointError, match=f"ckpt: damaged checkpoint .*patch 1.*{why}"):
        restore(chain, "ckpt", 1 << 20)


def test_what_is_not_a_chain_is_refused():
    for bad in (array_log.LoggedArrays(None, []),
                array_log.LoggedArrays(array_log.ArrayBase("t", 1, {"x": np.arange(2)}), [1]),
                array_log.LoggedArrays(array_log.ArrayBase("t", 1, {"x": 3}), [])):
        with pytest.raises(CheckpointError, match="ckpt: damaged checkpoint"):
            restore(bad, "ckpt", 1 << 20)


def test_the_log_lets_go_of_what_is_written():
    rng = np.random.default_rng(3)
    thing, log = _thing(rng, 100), ArrayLog(NAMES)
    chain = log.logged(thing).arrays
    thing.count[0] += 1
    chain = log.logged(thing).arrays
    base, patch = chain.base, chain.patches[0]
    log.written([log.name_of(base)])
    thing.count[1] += 1
    chain = log.logged(thing).arrays
    assert base.arrays == {} and patch.rows  # the written base's arrays are let go
    assert log.name_of(base) is not None  # its name stays: a capture names it
    log.written([log.name_of(patch)])
    log.logged(thing)
    assert patch.rows == {} and chain.patches[1].rows
