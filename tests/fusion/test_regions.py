"""The region graph: tiles linked by submaps that overlap them."""

from __future__ import annotations

import random

from fusion.regions import Region, region_of, regions


def _fleet() -> dict[str, list[tuple[int, int]]]:
    return {
        "a0": [(0, 0), (1, 0)],  # session a crosses from tile (0,0) into (1,0)
        "a1": [(1, 0)],
        "b0": [(1, 0), (1, 1)],  # session b links (1,1) in
        "c0": [(0, 2)],  # touches nothing the others touch: its own region (not adjacent-linked)
        "far": [(40, 40), (41, 40)],  # a far-away session
    }


def test_tiles_linked_by_overlap_and_far_session_alone() -> None:
    out = regions(_fleet())
    assert out == [
        Region(((0, 0), (1, 0), (1, 1)), ("a0", "a1", "b0")),
        Region(((0, 2),), ("c0",)),
        Region(((40, 40), (41, 40)), ("far",)),
    ]
    assert out[0].lower_corner == (0, 0)
    assert region_of(out, (41, 40)) == out[2]
    assert region_of(out, (5, 5)) is None


def test_order_independent() -> None:
    base = regions(_fleet())
    rng = random.Random(3)
    for _ in range(10):
        items = list(_fleet().items())
        rng.shuffle(items)
        shuffled = {k: rng.sample(v, len(v)) for k, v in items}
        assert regions(shuffled) == base


def test_restricted_to_requested_tiles() -> None:
    out = regions(_fleet(), only=[(0, 0), (1, 1)])
    # without (1, 0) nothing links (0, 0) and (1, 1)
    assert out == [Region(((0, 0),), ("a0",)), Region(((1, 1),), ("b0",))]
    assert regions({"x": []}) == []


def test_chain_merges_through_union() -> None:
    chain = {f"s{k}": [(k, 0), (k + 1, 0)] for k in range(6)}
    (r,) = regions(chain)
    assert r.tiles == tuple((k, 0) for k in range(7)) and len(r.submaps) == 6
