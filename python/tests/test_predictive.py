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


def test_predictive_filter_ignores_relative_degree_two():
    # no observation noise is defined for a higher derivative of h: the
    # condition of a relative-degree-2 barrier is the latent one
    from conftest import pendulum_data

    X, U, Xdot = pendulum_data(30, seed=2)
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1).fit(X, U, Xdot, max_iters=10)
    h = sector(2)
    a = bc.SafetyFilter(model, [h], probability=0.99, u_min=[-20], u_max=[20])
    b = bc.SafetyFilter(model, [h], probability=0.99, u_min=[-20], u_max=[20], predictive=True)
    x = [0.4, 0.1]
    ra, rb = a.filter(x, [1.0]), b.filter(x, [1.0])
    assert np.array_equal(ra.u, rb.u)
    assert ra.constraints[0]["std"] == rb.constraints[0]["std"]
