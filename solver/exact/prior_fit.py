"""The Gaussian-mixture fit of a non-Gaussian prior for the Yau–Hu filter (weighted EM on a grid).

Yau–Hu is exact for priors whose e^{−F}σ0 is a Gaussian mixture; any other prior is fitted here by
expectation–maximisation on a grid of the domain ball (the fit error is reported with the state).
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from ..gaussian import log_normal
from ..model import Model

_GRID = {1: 4001, 2: 161, 3: 41}


def fit_mixture_grid(model: Model):
    """Points of a regular grid inside the ball and the volume of one cell."""
    n = model.n
    axes = [np.linspace(c - model.radius, c + model.radius, _GRID[n]) for c in model.center]
    mesh = np.meshgrid(*axes, indexing="ij")
    X = np.stack([m.ravel() for m in mesh], axis=1)
    inside = np.linalg.norm(X - model.center, axis=1) <= model.radius
    return X[inside], float(np.prod([ax[1] - ax[0] for ax in axes]))


def weighted_em(X, w, K, iterations: int = 300):
    """Gaussian mixture fit of the weighted points (w sums to 1)."""
    n = X.shape[1]
    mean = w @ X
    cov = np.einsum("p,pi,pj->ij", w, X - mean, X - mean) + 1e-9 * np.eye(n)
    cdf = np.cumsum(w)
    picks = np.searchsorted(cdf, (np.arange(K) + 0.5) / K).clip(0, len(X) - 1)
    means = X[picks].astype(float)
    covs = np.stack([cov / K ** (2 / n)] * K)
    mix = np.full(K, 1.0 / K)
    floor = 1e-6 * np.trace(cov) / n * np.eye(n)
    for _ in range(iterations):
        logr = np.stack([np.log(mix[k]) + log_normal(X, means[k], covs[k]) for k in range(K)])
        resp = np.exp(logr - logsumexp(logr, axis=0)) * w
        mass = resp.sum(axis=1) + 1e-300
        mix = mass / mass.sum()
        means = (resp @ X) / mass[:, None]
        for k in range(K):
            dev = X - means[k]
            covs[k] = np.einsum("p,pi,pj->ij", resp[k], dev, dev) / mass[k] + floor
    return mix, means, covs
