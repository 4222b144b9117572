"""A submap's monocular drift (fusion.drift): the correction, and its estimate in the fine registration."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fusion.drift import Drift, ahead_axis, corrected_input, deform, jacobian
from fusion.drift_fit import fit_prior
from fusion.register import fine_register
from fusion.types import Pose, SemanticMesh, Sigma, SubmapInput
from tests.fusion.test_coarse import _block
from tests.scene import tiny_config


def test_scale_and_bend_grow_from_the_local_origin_along_the_axis_ahead() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0], [0.0, 5.0, 1.0]])
    scaled = Drift(math.log(1.01)).apply(pts)
    np.testing.assert_allclose(scaled, pts * 1.01)  # the origin holds, 20 m ahead moves 0.2 m
    k = math.radians(0.02)
    bent = Drift(0.0, k, k).apply(pts)
    np.testing.assert_allclose(bent[0], 0.0)
    # a heading (pitch) drift growing linearly with distance: κ x² / 2 sideways (up) at x ahead
    np.testing.assert_allclose(bent[1, 1:], [k * 400 / 2] * 2, rtol=1e-3)
    np.testing.assert_allclose(bent[2], pts[2], atol=1e-12)  # nothing ahead of the origin: nothing moves
    turned = Drift(0.0, k, 0.0, axis=(0.0, 1.0)).apply(np.array([[0.0, 20.0, 0.0]]))
    np.testing.assert_allclose(turned[0, 0], -k * 400 / 2, rtol=1e-3)  # the axis decides where "ahead" is


def test_the_axis_ahead_points_along_the_surface_towards_it() -> None:
    road = np.column_stack([np.linspace(-2.0, -40.0, 50), np.resize([-1.0, 1.0], 50), np.zeros(50)])
    np.testing.assert_allclose(ahead_axis(road), (-1.0, 0.0), atol=0.01)


def test_the_jacobian_matches_a_small_step_and_json_round_trips() -> None:
    pts = np.random.default_rng(0).uniform(-20, 20, (30, 3))
    p = np.array([0.01, 2e-4, -3e-4])
    axis = np.array([0.6, 0.8])
    step = np.array([1e-4, 1e-6, 2e-6])
    np.testing.assert_allclose(deform(pts, p + step, axis) - deform(pts, p, axis), jacobian(pts, p, axis) @ step,
                               atol=1e-6)  # second-order terms of a 20 m lever
    d = Drift(0.01, 2e-4, -3e-4, (0.6, 0.8))
    back = Drift.from_json(d.to_json())
    np.testing.assert_allclose(back.params, d.params)
    assert back.axis == d.axis and Drift.from_json(None).is_identity()


def test_a_corrected_input_carries_the_corrected_mesh_and_no_correction_changes_nothing() -> None:
    mesh = _block()
    sm = SubmapInput("a", "s", 0, mesh, Pose.identity(), Pose.identity())
    assert corrected_input(sm, None) is sm and corrected_input(sm, Drift()) is sm
    out = corrected_input(sm, Drift(math.log(1.02)))
    np.testing.assert_allclose(out.mesh.vertices, mesh.vertices * 1.02)
    np.testing.assert_array_equal(out.mesh.faces, mesh.faces)
    np.testing.assert_array_equal(sm.mesh.vertices, mesh.vertices)  # the upload is left as it was


def _drifted_pair(truth: Drift) -> list[SubmapInput]:
    """Session a holds the block exactly (fixed); session b uploads it under ``truth``'s drift, starting at the
    true pose. GPS 2 m / 2°."""
    exact = _block()
    uploaded = SemanticMesh(truth.apply(exact.vertices), exact.faces, exact.face_labels)
    sigma = Sigma(2.0, 2.0)
    return [SubmapInput("a", "sa", 0, exact, Pose.identity(), Pose.identity(), sigma, free=False,
                        pose_gps=Pose.identity()),
            SubmapInput("b", "sb", 0, uploaded, Pose.identity(), Pose.identity(), sigma, pose_gps=Pose.identity())]


def _misfit(subs: list[SubmapInput], drift_on: bool, fit_from: int | None = None) -> tuple[float, Drift]:
    """RMS distance (m) of b's vertices, corrected and posed as the registration found, from the truth.
    ``fit_from``: the drift priors fitted to the fleet from that many submaps (None: the fixed priors)."""
    start = [s.pose_init.matrix() for s in subs]
    gps = torch.tensor(np.stack([s.pose_gps.matrix() for s in subs]))
    fit = {"fine_drift_prior_fit": fit_from is not None, "fine_drift_prior_min_submaps": fit_from or 1}
    res = fine_register(subs, start, gps, tiny_config(fine_drift=drift_on, **fit))
    found = res.drifts[1]
    v = found.apply(subs[1].mesh.vertices)
    posed = v @ res.poses[1][:3, :3].T + res.poses[1][:3, 3]
    return float(np.sqrt(((posed - subs[0].mesh.vertices) ** 2).sum(1).mean())), found


@pytest.mark.parametrize("fit_from", [None, 1])
def test_the_registration_undoes_a_submaps_scale_and_bend_that_a_rigid_pose_cannot(fit_from: int | None) -> None:
    axis = ahead_axis(_block().vertices)
    truth = Drift(math.log(1.015), math.radians(0.02), math.radians(-0.02), axis)
    subs = _drifted_pair(truth)
    rigid, none = _misfit(subs, drift_on=False)
    corrected, found = _misfit(subs, drift_on=True, fit_from=fit_from)
    assert none.is_identity()
    assert rigid > 0.1, rigid  # the best rigid fit leaves the far corners decimetres off
    assert corrected < 0.3 * rigid and corrected < 0.04, (corrected, rigid)
    assert found.log_scale == pytest.approx(-truth.log_scale, abs=0.003)


def test_an_exact_submap_keeps_no_drift_and_less_with_the_priors_fitted_to_the_fleet() -> None:
    _, fixed = _misfit(_drifted_pair(Drift()), drift_on=True)
    assert abs(math.expm1(fixed.log_scale)) < 0.002 and np.degrees(np.abs(fixed.params[1:])).max() < 0.003
    _, fitted = _misfit(_drifted_pair(Drift()), drift_on=True, fit_from=1)
    assert np.abs(fitted.params).max() < 0.5 * np.abs(fixed.params).max(), (fitted.params, fixed.params)


def _em(truth: np.ndarray, noise: np.ndarray, ceiling: np.ndarray, updates: int, min_submaps: int = 8) -> np.ndarray:
    """``fit_prior``'s updates on a Gaussian model of a drift step: each submap's estimate the truth plus noise of
    σ ``noise``, its posterior under the current priors; returns the priors' σ after ``updates``."""
    y = truth + np.random.default_rng(0).normal(scale=noise, size=truth.shape)
    sigma = ceiling
    for _ in range(updates):
        shrink = sigma ** 2 / (sigma ** 2 + noise ** 2)
        sigma = fit_prior(y * shrink, np.broadcast_to(shrink * noise ** 2, y.shape), ceiling, min_submaps)
    return sigma


def test_the_fitted_prior_shrinks_without_drift_and_keeps_a_fleets_real_spread() -> None:
    ceiling = np.array([0.02, 7e-4, 7e-4])
    noise = ceiling / 10  # each estimate's own uncertainty
    none = _em(np.zeros((40, 3)), noise, ceiling, updates=8)
    assert (none < 0.2 * ceiling).all(), none  # estimates within their own noise: the prior closes on them
    spread = ceiling / 2
    real = _em(np.random.default_rng(1).normal(size=(40, 3)) * spread, noise, ceiling, updates=8)
    np.testing.assert_allclose(real, spread, rtol=0.3)  # a fleet that drifts keeps its spread
    few = _em(np.zeros((5, 3)), noise, ceiling, updates=8)
    np.testing.assert_array_equal(few, ceiling)  # fewer submaps than the fit needs: the configured priors


def test_the_drift_needs_the_gauss_newton_solver() -> None:
    with pytest.raises(ValueError, match="fine_drift needs fine_solver=gn"):
        tiny_config(fine_drift=True, fine_solver="lbfgs")
