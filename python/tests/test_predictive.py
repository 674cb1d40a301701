"""The predictive safety filter: the model's observation noise enters each
relative-degree-1 condition's variance, so the promise covers the step as
realised (SafetySettings::predictive)."""

from __future__ import annotations

import numpy as np

import bayes_cbf as bc
from conftest import sector


def test_predictive_filter_adds_the_observation_noise_to_the_variance(model):
    h = sector(1)
    pred = bc.SafetyFilter(model, [h], probability=0.99, u_min=[-20], u_max=[20],
                           predictive=True)
    noise_cov = model.noise_sigma**2 * model.row_cov
    for x in ([0.3, 0.2], [1.1, -0.4], [-0.5, 0.9]):
        r = pred.filter(x, [0.0])
        c = r.constraints[0]
        # the latent variance at the applied control, plus σ² ∇hᵀ A ∇h
        mean, var = bc.moments(model, h, x, r.u)
        g = np.asarray(h.gradient(x))
        added = float(g @ noise_cov @ g)
        assert added > 0
        assert abs(c["std"] ** 2 - (var + added)) <= 1e-9 * (var + added)
        # the mean is the latent one
        assert abs(mean - c["mean"]) <= 1e-9 * max(1.0, abs(mean))


def test_predictive_filter_widens_relative_degree_two_at_every_control(model):
    # the noise of the realised ∇(L_f h)ᵀ ẋ: a constant added to the
    # variance, the mean unchanged
    h = sector(2)
    # the paper's latent condition by default, as `bayes-cbf control`
    latent = bc.SafetyFilter(model, [h], probability=0.99, u_min=[-20], u_max=[20])
    pred = bc.SafetyFilter(model, [h], probability=0.99, u_min=[-20], u_max=[20],
                           predictive=True)
    x = [0.4, 0.1]
    added = []
    for u_ref in ([-15.0], [0.0], [15.0]):
        r = pred.filter(x, u_ref)
        mean, var = bc.moments(model, h, x, r.u)
        c = r.constraints[0]
        assert abs(mean - c["mean"]) <= 1e-9 * max(1.0, abs(mean))
        added.append(c["std"] ** 2 - var)
        rl = latent.filter(x, u_ref)
        assert abs(rl.constraints[0]["std"] ** 2 - bc.moments(model, h, x, rl.u)[1]) \
            <= 1e-9 * max(1.0, rl.constraints[0]["std"] ** 2)
    assert min(added) > 0
    assert max(added) - min(added) <= 1e-9 * max(added)
