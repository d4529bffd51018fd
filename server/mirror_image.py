"""A graph model served with its mirror image, the two halves on two cores.

A graph card with `mirror` (deepcontact.modelcard) is served by a MirroredGraphPredictor: its
network answers the step and the step reflected left to right (x -> -x), and the mean of the
answer and the reflected answer reflected back is served. Per point, with s_in (F,) and
s_out (T,) each channel's sign under the reflection (deepcontact.channels.mirror_signs):

    c  = net(x) * out_std + out_mean                                   (P, T)
    c' = (net(x') * out_std + out_mean) * s_out                        (P, T)
    x' = ((x * in_std + in_mean) * s_in - in_mean) / in_std            (P, F) normalized
    served: (c + c') / 2, combined with Box2D's warm start as the card says

the same numbers, to float32 rounding, as `python -m training.ensemble --mirror` builds into one
ONNX graph (its two steps a batch of two disjoint graphs). Why two calls: that batch doubles the
network's time on the step's critical path (about 0.17 ms of the default's step on the thesis
world); as two calls, the reflected half runs on a core that is otherwise idle while the step's
half runs, and its time is hidden. Where no core is spare (`spare` None) the halves run one
after the other in the calling thread, the same answer at twice the network's time; a caller
that cannot afford that asks for the step's half alone (`reflected=False`, the plain network's
answer).
"""

from __future__ import annotations

import concurrent.futures

import numpy as np

from deepcontact.channels import mirror_signs
from deepcontact.modelcard import ModelCard, ModelCardError
from server.predictors import GraphPredictor, Prediction


class MirroredGraphPredictor(GraphPredictor):
    """A graph card's network answering the step and its mirror image (module docstring).
    Takes what GraphPredictor takes; card.mirror must be set. A network with probes (which
    also reads the step's geometry) is not served so: its geometry would need reflecting too."""

    def __init__(self, card: ModelCard, onnx_path, **kwargs):
        if not card.mirror:
            raise ModelCardError(f"{card.name}: a card without mirror is served by GraphPredictor")
        super().__init__(card, onnx_path, **kwargs)
        if self.physics:
            raise ModelCardError(f"{card.name}: mirror serves a network without probes; this one reads the "
                                 "step's geometry (serve it through python -m training.ensemble --mirror)")
        spec = card.gridspec
        # The reflection acts on raw channel values; x is normalized, so x' = s_in x + shift.
        sign_in = mirror_signs(spec.inputs)
        self.sign_in = sign_in
        self.shift_in = (self.in_mean * (sign_in - 1) / self.in_std).astype(np.float32)
        self.sign_out = mirror_signs(spec.targets)

    def predict(self, bodies, points, world, step, previous=None, friction=None,
                spare: concurrent.futures.Executor | None = None, reflected: bool = True,
                meanwhile=None) -> Prediction:
        """As GraphPredictor.predict, the network's answer the mean of the step's and its
        mirror image's. spare: an executor whose thread answers the reflected half while this
        one answers the step's (None: both here, one after the other); reflected=False: the
        step's half alone, the plain network's answer; meanwhile: a callable of no arguments
        this thread runs after its half while the reflected half runs on spare (a caller's
        work that fills the wait: the face route's geometry)."""
        if not reflected:
            return self._predict(bodies, points, world, step, previous, friction, self.infer)
        return self._predict(bodies, points, world, step, previous, friction,
                             lambda x, ends, dynamic: self.both_halves(x, ends, dynamic, spare, meanwhile))

    def both_halves(self, x: np.ndarray, ends: np.ndarray, dynamic: np.ndarray,
                    spare: concurrent.futures.Executor | None = None, meanwhile=None) -> np.ndarray:
        """As run_session (x (P, F) float32 normalized, ends (P, 2) int32, dynamic (B, 1)
        float32 -> (P, T) normalized), the answer the mean of the network's on x and on its
        mirror image reflected back; the reflected half on `spare`'s thread where given, and
        `meanwhile` (predict) run here after this thread's half."""
        mirrored = x * self.sign_in + self.shift_in
        if spare is not None:
            other = spare.submit(self.infer, mirrored, ends, dynamic)
            y = self.infer(x, ends, dynamic)
            if meanwhile is not None:
                meanwhile()
            y_mirrored = other.result()
        else:
            y = self.infer(x, ends, dynamic)
            y_mirrored = self.infer(mirrored, ends, dynamic)
            if meanwhile is not None:
                meanwhile()
        # Denormalized, the reflected answer reflected back, their mean, normalized again for
        # the caller's denormalization.
        answer = y * self.out_std + self.out_mean
        answer += (y_mirrored * self.out_std + self.out_mean) * self.sign_out
        answer *= 0.5
        answer -= self.out_mean
        answer /= self.out_std
        return answer
