"""The fine registration's rounds (``fusion.register``): how far each round looks for a match, when the rounds stop
narrowing, and how much a round's matches count against the odometry and GPS priors. Functions of the config and
of residuals (m) only; no torch."""

from __future__ import annotations

import math

import numpy as np

from fusion.config import FusionConfig


def match_radii(config: FusionConfig, gps_sigma_m: float) -> np.ndarray:
    """The rounds' match radii (m): from ``fine_max_dist_m``, or ``fine_basin_sigmas`` × the submaps' GPS σ
    (``gps_sigma_m``, their median) where that is wider, shrinking geometrically to ``fine_min_dist_m``.

    Why σ: a session's odometry chain placed on its GPS fixes starts about σ from the others (σ 4 m:
    1.3-3 m per session on the bench), and a match is found only within the radius; from 2 m the widest
    round left exact sessions 1-1.4 m off (3×3 bench, σ 4 m, seeds 0-2: 0.72 / 1.02 / 0.84 m before the
    field) where 5 m brought them to 0.24 / 0.22 / 0.29 m. A wider start keeps the default schedule's
    shrink per round (``fine_rounds`` rounds over the default range), so it adds rounds instead of
    coarsening each step. :func:`fine_register` ends the schedule early where the surfaces disagree
    (:func:`spread_floor`)."""
    lo, hi = config.fine_min_dist_m, config.fine_max_dist_m
    if config.fine_rounds <= 1 or hi <= lo:
        return np.geomspace(hi, lo, max(1, config.fine_rounds))
    start = max(hi, config.fine_basin_sigmas * gps_sigma_m)
    per_round = math.log(hi / lo) / (config.fine_rounds - 1)
    rounds = max(config.fine_rounds, 1 + math.ceil(math.log(start / lo) / per_round - 1e-9))
    return np.geomspace(start, lo, rounds)


def spread_floor(config: FusionConfig, wall_spread_m: float | None) -> float:
    """The narrowest radius (m) a round may take given the robust spread of the other sessions' wall residuals
    after the previous round (``wall_spread_m``; None before the first): ``fine_spread_radius`` × it, within
    [``fine_min_dist_m``, ``fine_polish_max_m``] (``fine_min_dist_m`` with ``fine_spread_radius`` 0 or no spread).

    Why: a match survives only where a sample of the other session's surface lies within the radius, and
    the round's Cauchy scale is half the radius. Where the surfaces disagree by more than the schedule's
    last radius, the last rounds kept the patches that happened to agree and fitted each submap to them
    (a monocular camera's walls, robust spread ~0.13 m after a round at 0.8 m: at 0.25 m the registration
    tilted seed 3's submaps, 0.32° -> 0.36°). At 5 × the spread the Cauchy scale is 2.5 × it, and a match
    one spread off keeps 86 % of an agreeing one's weight. Exact surfaces (spread ~0.04 m) keep the
    schedule's 0.25 m, where their registration is cm-precise (exact seed 0: 0.111 m at 0.25 m, 0.156 m at
    0.75 m). The ceiling bounds an early round's spread, which still holds misalignment."""
    if config.fine_spread_radius <= 0 or wall_spread_m is None:
        return config.fine_min_dist_m
    top = max(config.fine_polish_max_m, config.fine_min_dist_m)
    return float(np.clip(config.fine_spread_radius * wall_spread_m, config.fine_min_dist_m, top))


WALL_SPREAD_MIN_MATCHES = 100  # fewer upright matches than this: no spread (spread_floor keeps the schedule)


def wall_spread(residual: np.ndarray, ground: np.ndarray) -> float | None:
    """The robust spread (m; 1.4826 × the median |residual|) of the upright matches' residuals (``ground``:
    per match, ground-like), None with fewer than ``WALL_SPREAD_MIN_MATCHES`` of them."""
    upright = residual[~ground]
    return float(1.4826 * np.median(np.abs(upright))) if len(upright) >= WALL_SPREAD_MIN_MATCHES else None


def data_gains(residual: np.ndarray, ground: np.ndarray, part: np.ndarray, sigma: float, config: FusionConfig,
           basin: bool) -> np.ndarray:
    """Per match of ``part`` (bool per match), :func:`noise_gain` of its kind at scale ``sigma``: ground-like
    matches by the ground's spread (only with ``fine_noise_ground``: a monocular road is offset in height by its
    submap's scale error while its residuals stay tight), the others by theirs; 1 in a basin round."""
    g, u = ground & part, ~ground & part
    return np.where(g, noise_gain(residual[g], sigma, config, config.fine_noise_ground and not basin),
                    noise_gain(residual[u], sigma, config, not basin))[part]


def own_gains(residual: np.ndarray, ground: np.ndarray, part: np.ndarray, session: np.ndarray, sigma: float,
               config: FusionConfig, basin: bool) -> np.ndarray:
    """Per own-overlap match of ``part`` (``session``: the matching session, per match), from its session's own
    residuals: the gain of its kind at the round's scale ``sigma`` (:func:`noise_gain`, ground-like and other
    matches each by their spread) times its *trust*, the gain the same residuals earn at the Cauchy scale
    ``fine_own_trust_m`` over ``fine_noise_max_gain``: exact overlaps, cm apart after a rigid fit, count nearly
    fully, a monocular session's, whose scale and bend leave dm, ~1/20. A ground-like match's two gains are let
    up from 1 only as far as the session's walls fit tighter than that scale
    (:func:`_excess`): as if ``fine_noise_ground`` were on for an exact session and off for a monocular one.

    Why per session and why the walls speak for the ground: a session's overlaps with itself repeat its own
    errors, so they are evidence as far as its submaps are rigid copies of one world. A monocular road fits as
    tight as an exact one while lying (s - 1) × the camera height too high or low for a scale error s; only
    the walls show that error (a wall r metres off moves by (s - 1) r). Zero in a basin round (rounds wider
    than ``fine_max_dist_m``) and without the gain."""
    out = np.zeros(int(part.sum()))
    if basin or config.fine_noise_max_gain <= 1:
        return out
    idx = np.flatnonzero(part)
    fine, top = config.fine_own_trust_m, config.fine_noise_max_gain
    for k in np.unique(session[idx]):
        mine = session[idx] == k
        g, u = ground[idx] & mine, ~ground[idx] & mine
        r_g, r_u = residual[idx[g]], residual[idx[u]]
        out[u] = noise_gain(r_u, sigma, config) * noise_gain(r_u, fine, config) / top
        if g.any():
            rigid = _excess(r_u, fine, config) if not config.fine_noise_ground else 1.0
            lift = [1.0 + (noise_gain(r_g, at, config) - 1.0) * rigid for at in (sigma, fine)]
            out[g] = lift[0] * lift[1] / top
    return out


def _excess(residual: np.ndarray, sigma: float, config: FusionConfig) -> float:
    """How far :func:`noise_gain` at ``sigma`` rises above 1, as a share of its range: 0 for residuals no
    tighter than ``sigma`` (or none), 1 at ``fine_noise_max_gain``."""
    if len(residual) == 0:
        return 0.0
    return (noise_gain(residual, sigma, config) - 1.0) / (config.fine_noise_max_gain - 1.0)


def noise_gain(residual: np.ndarray, sigma: float, config: FusionConfig, on: bool = True) -> float:
    """How many times ``fine_weight`` the round's data count: (σ / s)² with s the residuals' robust spread
    (1.4826 × their median absolute value, at least ``fine_noise_floor_m``), within [1, ``fine_noise_max_gain``];
    1 with ``fine_noise_max_gain`` ≤ 1.

    Why: the Cauchy scale σ follows the radius schedule, not the data, so a fixed weight made exact surfaces
    (residuals of ~3 cm) as soft as monocular ones (~15 cm); against that softness the odometry bent each
    session's chain by ~0.1 m between the places other sessions pin it (3×3 exact bench: 0.17 m after the
    rigid gauge). Early rounds, whose residuals are the misalignment itself, keep the base weight."""
    if not on or config.fine_noise_max_gain <= 1 or len(residual) == 0:
        return 1.0
    spread = max(config.fine_noise_floor_m, 1.4826 * float(np.median(np.abs(residual))))
    return float(np.clip((sigma / spread) ** 2, 1.0, config.fine_noise_max_gain))
