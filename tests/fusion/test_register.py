"""Fine registration (fusion.register): joint point-to-plane ICP of every submap before the field."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fusion.match_weights import match_radii, own_gains, spread_floor
from fusion.matching import HeldPairs, correspondences
from fusion.register import fine_register, surface_samples
from fusion.types import Pose, SemanticMesh, Sigma, SubmapInput
from tests.fusion.test_coarse import _block
from tests.scene import rot_z, tiny_config

CFG = tiny_config(fine_register=True)


def _pair(wrong: Pose, free_a: bool = True) -> list[SubmapInput]:
    """Two sessions of one submap each over the same block (the truth: both at identity); ``b`` starts at
    ``wrong``. GPS fixes at the truth, 2 m / 2°."""
    sigma = Sigma(2.0, 2.0)
    return [SubmapInput("a", "sa", 0, _block(), Pose.identity(), Pose.identity(), sigma, free=free_a,
                        pose_gps=Pose.identity()),
            SubmapInput("b", "sb", 0, _block(extra_box=True), wrong, Pose.identity(), sigma, pose_gps=Pose.identity())]


def _run(subs: list[SubmapInput], **changes: object):  # noqa: ANN202
    start = [s.pose_init.matrix() for s in subs]
    gps = torch.tensor(np.stack([s.pose_gps.matrix() for s in subs]))
    return fine_register(subs, start, gps, CFG.with_(**changes))


def _relative(poses: list[np.ndarray]) -> tuple[float, float]:
    rel = np.linalg.inv(poses[0]) @ poses[1]
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1))))


def test_a_submap_half_a_metre_and_two_degrees_off_is_registered_onto_the_other() -> None:
    wrong = Pose(np.array([0.6, -0.5, 0.3]), rot_z(2.0))
    res = _run(_pair(wrong))
    t, deg = _relative(res.poses)
    assert t < 0.05 and deg < 0.2, (t, deg)  # started 0.84 m / 2° apart
    rounds = res.metrics["rounds"]
    assert all(r["matches"] > 0 for r in rounds)
    assert rounds[-1]["median_residual_m"] < 0.02


def test_a_fixed_submap_holds_and_the_free_one_moves_onto_it() -> None:
    wrong = Pose(np.array([-0.5, 0.4, -0.2]), rot_z(-1.5))
    subs = _pair(wrong, free_a=False)
    res = _run(subs)
    np.testing.assert_allclose(res.poses[0], subs[0].pose_init.matrix(), atol=1e-12)
    t, deg = _relative(res.poses)
    assert t < 0.05 and deg < 0.2, (t, deg)


def test_submaps_farther_apart_than_the_largest_radius_are_not_matched_and_keep_their_poses() -> None:
    wrong = Pose(np.array([0.0, 60.0, 0.0]), rot_z(0.0))  # another street: nothing within 2 m
    subs = _pair(wrong)
    subs[1].pose_gps = wrong  # its GPS agrees: nothing pulls it
    res = _run(subs)
    assert all(r["matches"] == 0 for r in res.metrics["rounds"])
    for got, s in zip(res.poses, subs, strict=True):
        np.testing.assert_allclose(got, s.pose_init.matrix(), atol=1e-6)


def test_the_first_radius_widens_with_the_gps_sigma_and_keeps_the_shrink_per_round() -> None:
    default = match_radii(CFG, 1.0)  # 1.25 × 1 m < 2 m: the configured schedule
    np.testing.assert_allclose(default, np.geomspace(CFG.fine_max_dist_m, CFG.fine_min_dist_m, CFG.fine_rounds))
    wide = match_radii(CFG, 4.0)
    assert wide[0] == CFG.fine_basin_sigmas * 4.0 and wide[-1] == CFG.fine_min_dist_m
    assert len(wide) > len(default)  # more rounds, not coarser steps
    assert wide[1] / wide[0] >= default[1] / default[0] - 1e-9
    assert len(match_radii(CFG.with_(fine_basin_sigmas=0.0), 4.0)) == CFG.fine_rounds


def _far_pair(gps_sigma: float) -> list[SubmapInput]:
    """``b`` starts 5 m / 3° off, its GPS fix where it starts (nothing but the data pulls it back)."""
    wrong = Pose(np.array([4.0, -3.0, 0.2]), rot_z(3.0))
    subs = _pair(wrong)
    for s in subs:
        s.gps_sigma = Sigma(gps_sigma, gps_sigma)
    subs[1].pose_gps = wrong
    return subs


def test_a_submap_beyond_the_default_radius_is_registered_when_the_gps_sigma_says_it_can_be_that_far() -> None:
    t, deg = _relative(_run(_far_pair(5.0)).poses)  # first radius 6.25 m: the walls 5 m apart match
    assert t < 0.05 and deg < 0.2, (t, deg)
    t, _ = _relative(_run(_far_pair(1.0)).poses)  # radius 2 m: the ground and a few wrong walls, it stays off
    assert t > 3.0, t


def test_correspondences_skip_the_own_submap_and_disagreeing_normals() -> None:
    # submap 0: a floor point and a wall point; submap 1: a floor point 0.1 m above the first, a wall
    # point right next to submap 0's floor point (but facing sideways)
    posed = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.0, 0.0, 0.1], [0.02, 0.0, 0.0]])
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    owner = np.array([0, 0, 1, 1])
    src, dst = correspondences(posed, normals, owner, radius=0.5, min_dot=0.7)
    pairs = dict(zip(src.tolist(), dst.tolist(), strict=True))
    assert pairs[0] == 2  # floor to floor, though submap 1's wall point lies nearer
    assert pairs[1] == 3 and pairs[2] == 0 and pairs[3] == 1  # never a point of its own submap


def test_correspondences_within_a_group_only_for_the_samples_let_through() -> None:
    # the same four samples, both submaps of one session (group 0): none match; with the wall samples
    # let through (own-session matches on upright surfaces only), exactly the walls pair up
    posed = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.0, 0.0, 0.1], [0.02, 0.0, 0.0]])
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    owner, group = np.array([0, 0, 1, 1]), np.array([0, 0])
    src, _ = correspondences(posed, normals, owner, radius=0.5, min_dot=0.7, group=group)
    assert len(src) == 0
    walls = np.abs(normals[:, 2]) < 0.7
    src, dst = correspondences(posed, normals, owner, radius=0.5, min_dot=0.7, group=group, within=walls)
    assert dict(zip(src.tolist(), dst.tolist(), strict=True)) == {1: 3, 3: 1}


def _brute_force_matches(posed: np.ndarray, normals: np.ndarray, owner: np.ndarray, radius: float,
                         min_dot: float, k: int = 4) -> dict[int, int]:
    """The definition: per sample, over every other submap in order, the nearest of that submap's ``k``
    nearest samples within ``radius`` whose normal agrees; of two submaps equally near, the first."""
    out: dict[int, int] = {}
    for s in range(len(posed)):
        best = (np.inf, -1)
        for j in np.unique(owner):
            if j == owner[s]:
                continue
            mine = np.flatnonzero(owner == j)
            d = np.linalg.norm(posed[mine] - posed[s], axis=1)
            for c in np.argsort(d, kind="stable")[:k]:
                if d[c] < radius and normals[mine[c]] @ normals[s] >= min_dot:
                    if d[c] < best[0]:
                        best = (d[c], mine[c])
                    break
        if best[1] >= 0:
            out[s] = int(best[1])
    return out


def test_correspondences_are_the_nearest_agreeing_sample_of_another_submap_within_the_radius() -> None:
    # eight submaps strung along a street, each overlapping its neighbours in part: most samples lie outside
    # most other submaps' boxes (those are left unmatched without a query); the matches are the definition's
    rng = np.random.default_rng(11)
    owner = np.repeat(np.arange(8), 150)
    posed = rng.uniform(0, 1, (len(owner), 3)) * [6.0, 3.0, 0.3] + (owner[:, None] * [2.5, 0.4, 0.0])
    normals = rng.normal(0, 0.4, (len(owner), 3)) + [0, 0, 1]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    for radius in (0.6, 0.25):
        src, dst = correspondences(posed, normals, owner, radius, 0.8)
        want = _brute_force_matches(posed, normals, owner, radius, 0.8)
        assert len(want) > 100
        assert dict(zip(src.tolist(), dst.tolist(), strict=True)) == want


def test_held_pairs_kept_over_the_rounds_give_the_matches_of_a_fresh_query() -> None:
    # six submaps of noisy samples over one patch, four held: over shrinking radii (and one wider again) the
    # matches with the held pairs' queries kept are those of fresh queries, in both passes; fewer queries
    rng = np.random.default_rng(5)
    owner = np.repeat(np.arange(6), 300)
    posed = rng.uniform(0, 4, (len(owner), 3)) * [1, 1, 0.2]
    normals = rng.normal(0, 0.3, (len(owner), 3)) + [0, 0, 1]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    group = np.array([0, 0, 1, 1, 2, 2])
    held = HeldPairs(np.array([True, True, True, True, False, False]))
    for radius in (1.0, 0.5, 0.3, 0.3, 0.12, 0.6):
        for same in (False, True):
            fresh = correspondences(posed, normals, owner, radius, 0.7, group, same=same)
            kept = correspondences(posed, normals, owner, radius, 0.7, group, same=same, held=held)
            assert len(fresh[0]) > 0
            np.testing.assert_array_equal(kept[0], fresh[0])
            np.testing.assert_array_equal(kept[1], fresh[1])
    assert set(held.best) == {(i, j, same) for same in (False, True) for i in range(4) for j in range(4)
                              if i != j and (group[i] == group[j]) == same}


def test_the_alignment_start_runs_it_after_the_coarse_stage_and_the_switch_turns_it_off() -> None:
    from fusion.align import start_poses

    wrong = Pose(np.array([0.4, 0.3, 0.25]), rot_z(1.0))
    subs = _pair(wrong)
    cfg = CFG.with_(coarse_register=False, odom_init=False)
    on, metrics = start_poses(subs, cfg)
    t, _ = _relative([on["a"].matrix(), on["b"].matrix()])
    assert "fine" in metrics and t < 0.05
    off, metrics = start_poses(subs, cfg.with_(fine_register=False))
    assert "fine" not in metrics and np.allclose(off["b"].t, wrong.t)


def _corridor() -> SubmapInput:
    """A 40 m street along x: ground, two long walls facing across it (±y) and one post whose sides face
    along it (±x): what fixes the submap along the street is ~1 % of the vertical area."""
    import trimesh

    parts = [trimesh.creation.box(extents=(40.0, 8.0, 0.1)).apply_translation((20.0, 0.0, -0.05))]
    for y in (-4.0, 4.0):
        parts.append(trimesh.creation.box(extents=(40.0, 0.2, 3.0)).apply_translation((20.0, y, 1.5)))
    parts.append(trimesh.creation.box(extents=(0.3, 0.3, 3.0)).apply_translation((20.0, 2.0, 1.5)))
    mesh = trimesh.util.concatenate(parts)
    sm = SemanticMesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                      np.ones(len(mesh.faces), np.int64))
    return SubmapInput("c", "sc", 0, sm, Pose.identity(), Pose.identity(), Sigma(2.0, 2.0))


def test_normal_balance_spreads_vertical_samples_over_the_directions_they_face() -> None:
    sm = _corridor()
    shares = {}
    for balance in (0.0, 1.0):
        _, n = surface_samples(sm, 20_000, 4.0, np.random.default_rng(0), balance)
        vertical = np.abs(n[:, 2]) < 0.7
        along = np.abs(n[:, 0]) > 0.9  # the post's sides and the walls' ends: faces that fix x
        shares[balance] = (along.mean(), vertical.mean())
    (along_0, vertical_0), (along_1, vertical_1) = shares[0.0], shares[1.0]
    assert along_0 < 0.01 and along_1 > 8 * along_0, shares  # gain capped at AZIMUTH_MAX_GAIN (8×)
    assert abs(vertical_1 - vertical_0) < 0.02, shares  # ground vs vertical split unchanged


def test_a_whole_session_off_by_a_metre_is_moved_onto_the_other_not_held_by_its_own_submaps() -> None:
    # session b: three overlapping submaps on one odometry chain, all shifted 1 m; session a at the truth
    wrong = Pose(np.array([0.8, -0.6, 0.0]), rot_z(0.0))
    sigma = Sigma(2.0, 2.0)
    subs = [SubmapInput("a", "sa", 0, _block(), Pose.identity(), Pose.identity(), sigma, pose_gps=Pose.identity())]
    subs += [SubmapInput(f"b{k}", "sb", k, _block(extra_box=True), wrong, Pose.identity(), sigma,
                         pose_gps=Pose.identity()) for k in range(3)]
    res = _run(subs)
    for k in (1, 2, 3):
        t, deg = _relative([res.poses[0], res.poses[k]])
        assert t < 0.05 and deg < 0.2, (k, t, deg)


def test_the_odometry_and_gps_jacobian_matches_autograd() -> None:
    from fusion.poses import PoseSet
    from fusion.register import _chain_colours, _prior_jacobian, _prior_residuals
    from fusion.training import PoseTerms

    rng = np.random.default_rng(3)
    subs = []
    for k in range(5):  # two sessions, chains of 3 and 2, poses a few metres and degrees apart
        sid = "sa" if k < 3 else "sb"
        odo = Pose(rng.normal(size=3) * 3, rot_z(float(rng.normal() * 5)))
        init = Pose(rng.normal(size=3) * 3, rot_z(float(rng.normal() * 5)))
        subs.append(SubmapInput(f"m{k}", sid, k, _block(), init, odo, Sigma(1.5, 1.5), pose_gps=Pose.identity()))
    poses = torch.tensor(np.stack([s.pose_init.matrix() for s in subs]))
    cents = torch.tensor(rng.normal(size=(5, 3)) * 10)
    gps = torch.tensor(np.stack([Pose(rng.normal(size=3), rot_z(float(rng.normal()))).matrix() for _ in subs]))
    terms = PoseTerms.of(subs, torch.device("cpu"))
    got = _prior_jacobian(poses, cents, terms, gps, torch.tensor(_chain_colours(subs))).dense(5)

    def residuals(xi: torch.Tensor) -> torch.Tensor:
        ps = PoseSet(poses, cents, torch.ones(5, dtype=torch.bool))
        c = ps.to_centroid
        from fusion import se3
        return _prior_residuals(c @ se3.se3_exp(xi.reshape(5, 6)) @ se3.inverse(c) @ poses, terms, gps).reshape(-1)

    want = torch.autograd.functional.jacobian(residuals, torch.zeros(30, dtype=torch.float64))
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-5)


def _bent_chain() -> list[SubmapInput]:
    # session b: four submaps over session a's block, started on a bend (0, 0.3, 0.6, 0.9 m across and
    # 0-1.5° of yaw) while their odometry says they coincide; GPS 1.5 m at the truth
    sigma = Sigma(1.5, 1.5)
    subs = [SubmapInput("a", "sa", 0, _block(), Pose.identity(), Pose.identity(), sigma, pose_gps=Pose.identity())]
    for k in range(4):
        wrong = Pose(np.array([0.1 * k, 0.3 * k, 0.0]), rot_z(0.5 * k))
        subs.append(SubmapInput(f"b{k}", "sb", k, _block(extra_box=True), wrong, Pose.identity(),
                                Sigma(0.02, 0.05), pose_gps=Pose.identity()))
    return subs


def _bent_session(steps_per_round: int, solver: str):  # noqa: ANN202
    return _run(_bent_chain(), fine_steps=steps_per_round, fine_solver=solver, fine_drift=False)


def test_gauss_newton_registers_a_bent_chain_in_a_few_steps_per_round() -> None:
    res = _bent_session(5, "gn")
    assert all(r["steps"] <= 5 for r in res.metrics["rounds"])
    for k in range(1, 5):
        t, deg = _relative([res.poses[0], res.poses[k]])
        assert t < 0.02 and deg < 0.05, (k, t, deg)


def test_a_round_stops_once_a_step_moves_no_point_farther_than_the_tolerance() -> None:
    # the bent chain registered with the rounds run until the objective stops falling, and with them
    # stopped once a step moves every point by less than 0.1 mm: fewer steps, the same poses within that
    full = _run(_bent_chain(), fine_steps=30, fine_converged_m=0.0)
    early = _run(_bent_chain(), fine_steps=30, fine_converged_m=1e-4)
    steps = [sum(r["steps"] for r in res.metrics["rounds"]) for res in (full, early)]
    assert steps[1] < steps[0], steps
    for a, b in zip(full.poses, early.poses, strict=True):
        assert np.abs(a[:3, 3] - b[:3, 3]).max() < 1e-3


def test_the_lbfgs_solver_stays_available_and_registers_the_same_chain_given_steps() -> None:
    res = _bent_session(150, "lbfgs")
    for k in range(1, 5):
        t, deg = _relative([res.poses[0], res.poses[k]])
        assert t < 0.05 and deg < 0.2, (k, t, deg)


def test_an_unknown_solver_is_refused() -> None:
    import pytest

    with pytest.raises(ValueError, match="fine_solver"):
        CFG.with_(fine_solver="adam")


def test_the_data_count_more_the_tighter_they_agree_within_the_cap() -> None:
    from fusion.match_weights import noise_gain

    rng = np.random.default_rng(0)
    tight = rng.normal(scale=0.03, size=4000)  # exact surfaces: cm residuals
    loose = rng.normal(scale=0.5, size=4000)  # a round whose residuals are still the misalignment
    cfg = CFG.with_(fine_noise_max_gain=20.0)
    assert 15.0 < noise_gain(tight, 0.125, cfg) < 20.0  # (0.125 / 0.03)² ≈ 17
    assert noise_gain(tight, 0.125, cfg.with_(fine_noise_max_gain=5.0)) == 5.0
    assert noise_gain(loose, 0.125, cfg) == 1.0  # never below the base weight
    assert noise_gain(tight * 0.01, 0.125, cfg) == 20.0  # the floor keeps exact duplicates finite
    assert noise_gain(tight, 0.125, CFG.with_(fine_noise_max_gain=1.0)) == 1.0  # off


def test_the_polish_after_the_field_registers_what_the_field_left_a_few_decimetres_off() -> None:
    from fusion.align import _polish
    from fusion.poses import PoseSet

    subs = _pair(Pose(np.array([0.3, -0.25, 0.1]), rot_z(0.8)))  # where a field's noisy steps might leave b
    start = np.stack([s.pose_init.matrix() for s in subs])
    cents = np.stack([m[:3, :3] @ s.mesh.vertices.mean(0) + m[:3, 3] for m, s in zip(start, subs, strict=True)])
    poses = PoseSet(torch.tensor(start), torch.tensor(cents), torch.tensor([True, True]))
    gps = torch.tensor(np.stack([s.pose_gps.matrix() for s in subs]))
    cfg = CFG.with_(fine_polish_rounds=3, fine_polish_max_m=0.75, fine_min_dist_m=0.25)
    polished, metrics = _polish(subs, poses, gps, cfg, torch.device("cpu"), gain=1.0)  # the registration's own weight
    assert [round(r["radius_m"], 3) for r in metrics["rounds"]] == [0.75, 0.433, 0.25]
    t, deg = _relative(list(polished().detach().numpy()))
    assert t < 0.02 and deg < 0.1, (t, deg)


def test_the_sparse_normal_equations_equal_the_dense_ones_of_autograd_jacobians() -> None:
    # a region of 3 sessions × 4 submaps (data between neighbours and across sessions, odometry, GPS),
    # one submap held fixed: the block-sparse JᵀWJ and JᵀWr over the free twists equal the dense matrices
    # built from autograd Jacobians of the residuals
    from fusion import se3
    from fusion.eval.perf_register import synthetic_region
    from fusion.register import _linearise, _prior_residuals

    poses, match, terms, gps, local_cents, colour = synthetic_region(12, 3, 20, seed=4)
    local_cents = torch.randn(12, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    free = torch.ones(12, dtype=torch.bool)
    free[5] = False
    free_dofs = np.flatnonzero(free.repeat_interleave(6).numpy())
    h, g, cents = _linearise(poses, match, terms, gps, local_cents, colour, free_dofs)

    c = torch.eye(4, dtype=torch.float64).repeat(12, 1, 1)
    c[:, :3, 3] = cents

    def moved(xi: torch.Tensor) -> torch.Tensor:
        return c @ se3.se3_exp(xi.reshape(12, 6)) @ se3.inverse(c) @ poses

    zero = torch.zeros(72, dtype=torch.float64)
    r = match.residual(poses)
    weight = match.w / (match.sigma ** 2 + r * r)
    j_m = torch.autograd.functional.jacobian(lambda xi: match.residual(moved(xi)), zero)
    j_p = torch.autograd.functional.jacobian(lambda xi: _prior_residuals(moved(xi), terms, gps).reshape(-1), zero)
    dense = j_m.T @ (weight[:, None] * j_m) + j_p.T @ j_p
    grad = j_m.T @ (weight * r) + j_p.T @ _prior_residuals(poses, terms, gps).reshape(-1)
    assert h.shape == (66, 66) and h.nnz < 66 * 66
    np.testing.assert_allclose(h.toarray(), dense[free_dofs][:, free_dofs].numpy(), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(g, grad[free_dofs].numpy(), rtol=1e-5, atol=1e-4)


def test_the_solver_scaling_benchmark_aligns_its_synthetic_region() -> None:
    from fusion.eval.perf_register import run

    lines: list[str] = []
    (row,) = run([30], sessions=3, matches=30, steps=3, out=lines.append)
    assert row["submaps"] == 30 and row["steps"] >= 1
    assert row["final_rms_m"] < 0.1 * row["start_rms_m"]
    assert lines and "s/step" in lines[0]


def _lone_session(mesh_b: SemanticMesh) -> list[SubmapInput]:
    """One session of two submaps over the same block; the second starts (and its odometry and GPS say it
    is) 0.39 m / 0.6° off, loose odometry (0.3 m / 1°): no other session to register onto."""
    wrong = Pose(np.array([0.3, -0.25, 0.05]), rot_z(0.6))
    odometry = Sigma(0.3, 1.0)
    return [SubmapInput("a0", "sa", 0, _block(), Pose.identity(), Pose.identity(), Sigma(2.0, 2.0), odometry,
                        pose_gps=Pose.identity()),
            SubmapInput("a1", "sa", 1, mesh_b, wrong, wrong, Sigma(2.0, 2.0), odometry, pose_gps=wrong)]


def _distorted(mesh: SemanticMesh) -> SemanticMesh:
    """A monocular submap's errors: 3 % scale about its centroid and a bend sideways and up (κ x²)."""
    d = mesh.vertices - mesh.vertices.mean(0)
    v = mesh.vertices.mean(0) + 1.03 * d
    v[:, 1:] += 0.002 * d[:, :1] ** 2
    return SemanticMesh(v, mesh.faces, mesh.face_labels)


def test_a_sessions_own_overlaps_hold_its_chain_as_far_as_they_fit_rigidly() -> None:
    """``fine_own_overlap``: consecutive submaps of one session match each other too, weighted by how well
    they fit rigidly at the finest radius (ground-like matches only with ``fine_noise_ground``: a monocular
    road's height bias leaves tight residuals). Exact surfaces pull the second onto the first (0.39 m → cm);
    distorted ones (scale and bend, as a monocular session's) barely move it, since matching them stiffly
    would hand their distortion on to the chain. Off, a session's own overlaps are not matched at all."""
    exact = _lone_session(_block(extra_box=True))
    assert _relative(_run(exact, fine_own_overlap=False).poses)[0] > 0.38  # off: only other sessions are matched; there are none
    t, deg = _relative(_run(exact, fine_own_overlap=True).poses)
    assert t < 0.04 and deg < 0.1, (t, deg)
    res = _run(_lone_session(_distorted(_block(extra_box=True))), fine_own_overlap=True)
    assert res.metrics["rounds"][-1]["matches"] > 100
    assert _relative(res.poses)[0] > 0.3  # matched, but trusted ~1/20 of an exact overlap


def test_a_sessions_own_ground_counts_only_as_far_as_its_walls_fit_rigidly() -> None:
    """Own-overlap weights per session: a monocular session's road fits as tight as an exact one's (its scale
    error lifts it as a whole) but its walls do not; only the session whose walls fit within cm has its
    ground weighted by its spread. Each session by its own residuals, whatever the other's."""
    rng = np.random.default_rng(0)
    n = 400
    cfg = CFG.with_(fine_noise_max_gain=20.0, fine_noise_floor_m=0.02, fine_own_trust_m=0.125)
    # per session: walls, then ground; exact walls ~2 cm, monocular walls ~20 cm, every road ~1 cm
    residual = np.concatenate([rng.normal(0, 0.02, n), rng.normal(0, 0.01, n),
                               rng.normal(0, 0.20, n), rng.normal(0, 0.01, n)])
    ground = np.tile(np.repeat([False, True], n), 2)
    session = np.repeat([0, 1], 2 * n)
    part = np.ones(4 * n, bool)
    w = own_gains(residual, ground, part, session, 0.5, cfg, basin=False)
    exact_walls, exact_ground, mono_walls, mono_ground = (w[k * n:(k + 1) * n] for k in range(4))
    assert exact_walls.min() > 10 and exact_ground.min() > 10  # ~18 and ~15: nearly fully trusted
    np.testing.assert_allclose(mono_ground, 1 / 20)  # the ground rule: gain 1, trust 1/20
    assert mono_walls.max() < 0.5  # (0.5 / 0.2)² × 1/20
    alone = own_gains(residual[2 * n:], ground[2 * n:], part[2 * n:], session[2 * n:], 0.5, cfg, basin=False)
    np.testing.assert_allclose(alone, np.concatenate([mono_walls, mono_ground]))  # the other session has no say
    lifted = own_gains(residual, ground, part, session, 0.5, cfg.with_(fine_noise_ground=True), basin=False)
    assert lifted[3 * n:].min() > 10  # fine_noise_ground: every session's ground by its spread
    assert not own_gains(residual, ground, part, session, 0.5, cfg, basin=True).any()
    # the trust is earned at fine_own_trust_m, whatever the finest match radius
    np.testing.assert_allclose(own_gains(residual, ground, part, session, 0.5, cfg.with_(fine_min_dist_m=0.75),
                                          basin=False), w)
    assert own_gains(residual, ground, part, session, 0.5, cfg.with_(fine_own_trust_m=0.05), basin=False)[:n].max() < 10


def test_the_polish_trusts_matches_against_biased_odometry_as_far_as_they_proved_tight() -> None:
    from fusion.align import _polish
    from fusion.poses import PoseSet

    # session b: four submaps truly over session a's block (all at identity), whose odometry claims 0.15 m of
    # travel per submap; the field left them spread along that odometry. The surfaces say where they are: the
    # more the polish's matches count against the odometry prior (fine_weight × the registration's data gain,
    # capped), the closer b ends to the truth.
    subs = [SubmapInput("a", "sa", 0, _block(), Pose.identity(), Pose.identity(), Sigma(1.5, 1.5),
                        pose_gps=Pose.identity())]
    for k in range(4):
        subs.append(SubmapInput(f"b{k}", "sb", k, _block(extra_box=True), Pose(np.array([0.15 * (k - 1.5), 0.0, 0.0]),
                                rot_z(0.0)), Pose(np.array([0.15 * k, 0.0, 0.0]), rot_z(0.0)), Sigma(1.5, 1.5),
                                odometry_sigma=Sigma(0.05, 0.5), pose_gps=Pose.identity()))
    start = np.stack([s.pose_init.matrix() for s in subs])
    cents = np.stack([m[:3, :3] @ s.mesh.vertices.mean(0) + m[:3, 3] for m, s in zip(start, subs, strict=True)])
    gps = torch.tensor(np.stack([s.pose_gps.matrix() for s in subs]))

    def spread(gain: float, cap: float = 4.0) -> tuple[float, float]:
        poses = PoseSet(torch.tensor(start), torch.tensor(cents), torch.ones(len(subs), dtype=torch.bool))
        polished, metrics = _polish(subs, poses, gps, CFG.with_(fine_weight=5.0, fine_polish_gain_max=cap, fine_min_dist_m=0.25),
                                    torch.device("cpu"), gain)
        final = polished().detach().numpy()
        return max(_relative([final[0], m])[0] for m in final[1:]), metrics["weight"]  # b's farthest submap from a

    (loose, w_loose), (tight, w_tight) = spread(1.0), spread(16.0)
    assert (w_loose, w_tight) == (5.0, 20.0)  # a gain below 1 never lowers the weight; above the cap it stops
    assert spread(0.5)[1] == 5.0 and spread(16.0, cap=1.0)[1] == 5.0
    assert tight < 0.3 * loose, (loose, tight)  # 0.0057 against 0.022 m, one machine


def _warped(mesh: SemanticMesh, seed: int, amplitude: float) -> SemanticMesh:
    """``mesh`` with every vertex moved by a smooth random field (sines of 6–14 m wavelength, ± ``amplitude``
    per axis): a monocular pipeline's surface, wrong by decimetres in patches, right on average."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices
    shift = np.zeros_like(v)
    for axis in range(3):
        for _ in range(4):
            k = rng.normal(size=2)
            k *= 2 * np.pi / rng.uniform(6.0, 14.0) / np.linalg.norm(k)
            shift[:, axis] += amplitude / 4 * np.sin(v[:, :2] @ k + rng.uniform(0, 2 * np.pi))
    return SemanticMesh(v + shift, mesh.faces, mesh.face_labels)


def test_the_last_round_does_not_select_the_matches_where_monocular_surfaces_happen_to_agree() -> None:
    """A match survives a round only where a sample of the other surface lies within its radius, so a narrow last
    round drops the matches of surfaces that disagree by decimetres first: two sessions' monocular surfaces at
    their true poses, each wrong by up to ~0.3 m in smooth patches, against the same surfaces exact. At 0.25 m
    (the old default) the monocular pair kept ~3/4 of the share of its first round's matches the exact pair kept
    (exact 0.30, monocular 0.23: samples ~0.5 m apart leave few within 0.25 m at all), and the fit followed the
    patches that agree; at 0.75 m both keep the same share (0.88), so each submap is fitted to the mean of its
    disagreement with the others (camera seeds 0-3, registration alone: height error 0.13-0.16 m at 0.25 m,
    0.11-0.13 m at 0.75 m; docs/METHOD_LOG.md, "The finest radius")."""

    def kept(amplitude: float, last: float) -> float:
        rng = np.random.default_rng(0)
        meshes = [_warped(_block(), 1, amplitude), _warped(_block(extra_box=True), 2, amplitude)]
        subs = [SubmapInput(n, f"s{n}", 0, m, Pose.identity(), Pose.identity(), Sigma(1.5, 1.5))
                for n, m in zip("ab", meshes, strict=True)]
        pts, nrm = zip(*(surface_samples(s, 2000, 4.0, rng) for s in subs), strict=True)
        posed, normals, owner = np.concatenate(pts), np.concatenate(nrm), np.repeat([0, 1], 2000)
        first, then = (len(correspondences(posed, normals, owner, r, 0.7)[0]) for r in (CFG.fine_max_dist_m, last))
        return then / first

    assert kept(0.3, 0.75) > 0.95 * kept(0.0, 0.75)
    assert kept(0.3, 0.25) < 0.85 * kept(0.0, 0.25)


def _warped_pair(amplitude: float) -> list[SubmapInput]:
    """``_pair``'s two sessions, their surfaces ``_warped`` by ± ``amplitude`` m; ``b`` 0.36 m / 1° off."""
    subs = _pair(Pose(np.array([0.3, -0.2, 0.1]), rot_z(1.0)))
    for seed, s in enumerate(subs, 1):
        s.mesh = _warped(s.mesh, seed, amplitude)
    return subs


def test_the_rounds_stop_narrowing_where_the_sessions_surfaces_disagree() -> None:
    """The schedule's last radius (``fine_min_dist_m``) suits surfaces that agree to cm; where two sessions' walls
    disagree by decimetres (a monocular camera's), the rounds stop at ``fine_spread_radius`` × the robust spread of
    the wall residuals instead (fusion.match_weights.spread_floor), so the last round does not select the patches that
    happen to agree (the test above)."""
    exact = _run(_warped_pair(0.0)).metrics["rounds"]
    assert exact[-1]["radius_m"] == CFG.fine_min_dist_m and len(exact) == len(match_radii(CFG, 2.0))
    assert exact[-1]["wall_spread_m"] < 0.01
    mono = _run(_warped_pair(0.3)).metrics["rounds"]
    spread = mono[-2]["wall_spread_m"]  # ~0.1 m
    assert 0.07 < spread < 0.15, spread
    assert len(mono) < len(exact) and mono[-1]["radius_m"] == pytest.approx(CFG.fine_spread_radius * spread)
    assert all(r["radius_m"] >= 0.5 for r in mono)
    off = _run(_warped_pair(0.3), fine_spread_radius=0.0).metrics["rounds"]  # the schedule to its end
    assert [r["radius_m"] for r in off] == pytest.approx(match_radii(CFG, 2.0).tolist())


def test_the_spread_floor_lies_between_the_schedules_last_radius_and_the_polishs_first() -> None:
    assert spread_floor(CFG, None) == CFG.fine_min_dist_m  # before the first round
    assert spread_floor(CFG, 0.01) == CFG.fine_min_dist_m  # exact surfaces: the schedule's own end
    assert spread_floor(CFG, 0.12) == pytest.approx(CFG.fine_spread_radius * 0.12)
    assert spread_floor(CFG, 0.5) == CFG.fine_polish_max_m  # an early round's spread holds misalignment too
    assert spread_floor(CFG.with_(fine_spread_radius=0.0), 0.12) == CFG.fine_min_dist_m
