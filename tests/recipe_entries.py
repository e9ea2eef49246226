"""Registry entries a user might add, for the tests that follow the README's recipes ("Adding a
fusion rule", ...): each one is what the recipe tells a user to write, nothing more."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from covnet.core.gaussian import Gaussian, symmetrise
from covnet.covariance_control.fusion_rules import _TrackRule


class Naive(_TrackRule):
    """A user's rule: the local tracks' information added *without* removing their priors (the
    textbook double-counting mistake), scored as it fuses."""

    name: ClassVar[str] = "naive"
    information_form: ClassVar[bool] = False
    refilters_late: ClassVar[bool] = False

    def label(self):
        return self.name

    def fuse(self, model, prior, received):
        ordered = [t for _, t in sorted(received, key=lambda jt: jt[0])]
        if not ordered:
            return prior
        Y = np.linalg.inv(prior.P) + sum(np.linalg.inv(t.post.P) for t in ordered)
        y = np.linalg.solve(prior.P, prior.x) + sum(
            np.linalg.solve(t.post.P, t.post.x) for t in ordered
        )
        P = symmetrise(np.linalg.inv(Y))
        return Gaussian(P @ y, P)

    def candidates(self, model, P_prior, P_local_post, masks):
        Yl = np.linalg.inv(P_local_post)
        Y = np.linalg.inv(P_prior) + np.einsum("mj,jab->mab", masks.astype(float), Yl)
        return symmetrise(np.linalg.inv(Y))

    def fused_covariance(self, model, P_prior, P_local_post, subset):
        if not subset:
            return P_prior
        mask = np.zeros((1, P_local_post.shape[0]), dtype=bool)
        mask[0, list(subset)] = True
        return self.candidates(model, P_prior, P_local_post, mask)[0]

    def late_measurement(self, payload):
        return None
