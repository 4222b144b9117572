"""The region graph: tiles linked by submaps that overlap them."""

from __future__ import annotations

import random

import pytest

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


def test_needs_realignment_once_a_share_of_the_sessions_came_incrementally() -> None:
    """The joint re-alignment rule: a share of the region's sessions (the arriving one counted) aligned
    against a held map; one session alone, or none incremental, never; the share validated."""
    from fusion.config import FusionConfig
    from fusion.regions import needs_realignment

    third = FusionConfig().realign_share
    assert not needs_realignment(5, 1, third)  # a fifth session added to four: incremental
    assert needs_realignment(5, 2, third)  # the second one in a row: re-align
    assert needs_realignment(2, 1, third)  # a second session: a small map is re-aligned
    assert not needs_realignment(1, 1, third) and not needs_realignment(7, 0, third)
    assert not needs_realignment(5, 5, 1.01)  # > 1: never
    with pytest.raises(ValueError, match="realign_share"):
        FusionConfig(realign_share=0.0)
    half = FusionConfig(align_iterations_per_tile=300, realign_iterations_fraction=0.5)
    assert half.for_realignment().align_iterations_per_tile == 150 and half.align_iterations_per_tile == 300
    with pytest.raises(ValueError, match="realign_iterations_fraction"):
        FusionConfig(realign_iterations_fraction=1.5)
    # geometric: a map growing one session at a time from three joint sessions re-aligns at 5, 8, 12, 18
    incremental, realigned = 0, []
    for n in range(4, 20):
        incremental += 1
        if needs_realignment(n, incremental, third):
            incremental = 0
            realigned.append(n)
    assert realigned == [5, 8, 12, 18]
