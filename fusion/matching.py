"""The fine registration's correspondences (``fusion.register``): each surface sample's nearest sample of
another submap whose normal agrees, within a round's radius, by one k-d query per target submap; and the
matches between held submaps, kept over the rounds of an addition's registration (they do not move)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fusion.runtime import cpu_threads

# a k-d query of this many points or more runs on every thread (fusion.runtime.cpu_threads): one of a
# submap's 2000 samples ran slower on two threads (thread start-up)
PARALLEL_QUERY_POINTS = 10_000


class HeldPairs:
    """The matches between two held submaps, kept over a registration's rounds. Neither moves, so a round's
    matches at a radius r no wider than the first's R are the first's nearer than r: the k nearest within r
    are those of the k nearest within R that lie within r, and the nearest of them whose normal agrees is
    the one found within R if that lies within r (else none does). An addition registers a session's
    submaps against a held map whose submaps overlap each other far more than the new ones: most of a
    round's queries were these (exact seed 1 bench, 40 of 54 submaps held). ``held``: per submap."""

    def __init__(self, held: np.ndarray) -> None:
        self.held = held
        self.best: dict[tuple[int, int, bool], tuple[float, np.ndarray, np.ndarray]] = {}
        self.trees: dict[int, cKDTree] = {}

    def tree(self, i: int, points: np.ndarray) -> cKDTree:
        """Submap ``i``'s k-d tree over its posed samples ``points``: built once where it is held."""
        if not self.held[i]:
            return cKDTree(points)
        if i not in self.trees:
            self.trees[i] = cKDTree(points)
        return self.trees[i]

    def kept(self, i: int, j: int, same: bool, radius: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Per sample of ``i``: distance and index of its match in ``j`` within ``radius`` (inf where none),
        from a query at a radius no narrower, where both are held; else None (query and :meth:`keep` it).
        ``same``: the own-session pass's (its masks differ)."""
        if not (self.held[i] and self.held[j]):
            return None
        hit = self.best.get((i, j, same))
        if hit is None or hit[0] < radius:
            return None
        wider, dist, match = hit
        return (dist, match) if wider == radius else (np.where(dist < radius, dist, np.inf), match)

    def keep(self, i: int, j: int, same: bool, radius: float, dist: np.ndarray, match: np.ndarray) -> None:
        """Keep a fresh query's matches of a held pair (see :meth:`kept`)."""
        if self.held[i] and self.held[j]:
            self.best[(i, j, same)] = (radius, dist, match)


def correspondences(posed: np.ndarray, normals: np.ndarray, owner: np.ndarray, radius: float, min_dot: float,
                     group: np.ndarray | None = None, within: np.ndarray | None = None, same: bool = False,
                     held: HeldPairs | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(source, target) sample indices: each sample's nearest sample of another submap within ``radius``
    whose normal agrees with its own (dot ≥ ``min_dot``; none: unmatched), never of a submap in the same
    ``group`` (per submap index; default: each its own, i.e. only the own submap) unless the sample is one of
    ``within`` (per sample, bool: these match the other submaps of their group too); ``same``: the other way
    round, only the other submaps of the own group (a session's own overlaps). One k-d tree per submap, each
    sample queried against the submaps whose boxes (grown by ``radius``) hold it: linear in the
    overlaps, not quadratic in the region's submaps; a single tree over all samples would let a submap's
    own samples, denser nearby, hide the others'. Each tree is queried once with the samples of every submap
    that may match it (on every thread where they are many). ``held``: the matches between held submaps,
    kept over the rounds (the same matches, fewer queries)."""
    k = 4
    order = np.argsort(owner, kind="stable")  # each submap's samples, in sample order, as one slice
    ids, first = np.unique(owner[order], return_index=True)
    members = dict(zip(ids, np.split(order, first[1:]), strict=True))
    points = {i: posed[m] for i, m in members.items()}
    trees = {i: held.tree(int(i), p) if held is not None else cKDTree(p) for i, p in points.items()}
    lo = np.stack([points[i].min(0) for i in ids]) - radius
    hi = np.stack([points[i].max(0) for i in ids]) + radius
    # (source, target): boxes within reach, never the own submap
    meet = ~((lo[None, :] > hi[:, None]).any(-1) | (hi[None, :] < lo[:, None]).any(-1) | np.eye(len(ids), dtype=bool))
    if group is not None:
        g = group[ids]
        meet &= (g[:, None] == g[None, :]) if same else ((g[:, None] != g[None, :]) | (within is not None))
    # the submap pairs to match, with each source sample's mask, by source then target
    pairs: dict[tuple[int, int], np.ndarray] = {}
    for a, b in np.argwhere(meet):
        i, j = int(ids[a]), int(ids[b])
        if not same and group is not None and group[j] == group[i]:
            pairs[(i, j)] = within[members[i]]  # type: ignore[index]  # (meet: within is given)
        else:
            pairs[(i, j)] = np.ones(len(members[i]), bool)
    # per pair, each source sample's nearest agreeing sample of the target: the held pairs' kept over the
    # rounds, the others' in one query per target tree (its sources' samples together, on every thread)
    nearest: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    asks: dict[int, list[int]] = {}
    for (i, j) in pairs:
        kept = held.kept(i, j, same, radius) if held is not None else None
        if kept is not None:
            nearest[(i, j)] = kept
        else:
            asks.setdefault(j, []).append(i)
    # only the samples inside a target's box grown by the radius can have a match within it (on the bench a
    # third of those the boxes' overlap lets through): the others are left unmatched without a query
    box_of = {int(i): b for b, i in enumerate(ids)}
    targets_of: dict[int, list[int]] = {}
    for j, sources in asks.items():
        for i in sources:
            targets_of.setdefault(i, []).append(j)
    inside_of: dict[tuple[int, int], np.ndarray] = {}
    for i, js in targets_of.items():
        b = [box_of[j] for j in js]
        hit = np.all((points[i][:, None] >= lo[b][None]) & (points[i][:, None] <= hi[b][None]), axis=-1)
        for col, j in enumerate(js):
            inside_of[(i, j)] = np.flatnonzero(pairs[(i, j)] & hit[:, col])
    for j, sources in asks.items():
        inside = [inside_of[(i, j)] for i in sources]
        rows = np.concatenate([members[i][k_in] for i, k_in in zip(sources, inside, strict=True)])
        d_first, c_first = np.full(len(rows), np.inf), np.zeros(len(rows), np.int64)
        if len(rows):
            workers = cpu_threads() if len(rows) >= PARALLEL_QUERY_POINTS else 1
            dist, idx = trees[j].query(posed[rows], k=k, distance_upper_bound=radius, workers=workers)
            valid = np.isfinite(dist)
            cand = members[j][np.where(valid, idx, 0)]
            valid &= np.einsum("nkd,nd->nk", normals[cand], normals[rows]) >= min_dot
            d = np.where(valid, dist, np.inf)
            first = np.argmin(d, axis=1)
            at = np.arange(len(rows))
            d_first, c_first = d[at, first], cand[at, first]
        start = 0
        for i, k_in in zip(sources, inside, strict=True):
            end = start + len(k_in)
            d_pair, c_pair = np.full(len(members[i]), np.inf), np.full(len(members[i]), members[j][0])
            d_pair[k_in], c_pair[k_in] = d_first[start:end], c_first[start:end]
            nearest[(i, j)] = (d_pair, c_pair)
            if held is not None:
                held.keep(i, j, same, radius, *nearest[(i, j)])
            start = end
    src, dst = [], []
    targets: dict[int, list[int]] = {}
    for i, j in pairs:  # by source, then target in order: of two targets equally near, the first wins
        targets.setdefault(i, []).append(j)
    for i, js in targets.items():
        mine = members[i]
        best_d = np.full(len(mine), np.inf)
        best_j = np.full(len(mine), -1)
        for j in js:
            d_first, c_first = nearest[(i, j)]
            better = d_first < best_d
            best_d[better] = d_first[better]
            best_j[better] = c_first[better]
        has = best_j >= 0
        src.append(mine[has])
        dst.append(best_j[has])
    if not src:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(src), np.concatenate(dst)
