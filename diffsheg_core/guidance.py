"""One sampling step's noise prediction: the passes the network runs and how they are mixed.

A step is two network calls (see `runtime.backends`): the expression branch, then the
gesture branch, which sees the expression x0 made from the *mixed* expression noise.
Each call runs a small batch of passes over the same window:

- classifier-free guidance (scale w, models trained with a null speech condition): a
  null-conditioned and a conditioned pass, mixed as u + w (c - u);
- gesture skip guidance (scale s, after Spatiotemporal Skip Guidance, Hyung et al. 2024):
  the gesture branch with and without its self-attention blocks, mixed as c + s (c - k).
  The network without its temporal context predicts small, blurred gestures; steering away
  from it restores the amplitude small networks lose. It replaces the gesture branch's
  classifier-free pass, so a guided step costs two passes per branch either way;
- style guidance (scale g, models trained with a null style; DiffuseStyleGesture): one
  more gesture pass with the null style (all zeros), mixed in as + (g - 1) (c - n), so the
  result is n + g (c - n) besides the other guidance: 1 is the style as given, above 1
  goes beyond it. It steers the gestures only; the face keeps its style as given.

All numpy: the mixing is the same whichever backend runs the passes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol, Union

import numpy as np


class Network(Protocol):
    """The two calls of a UniEG network on numpy arrays (batch B, window length L).
    null: (B,) bool, rows that see the learned null condition; attend: (B,) bool, false for
    rows without self-attention; None: no row nulled / every row attends."""

    def expression(self, expression: np.ndarray, timesteps: np.ndarray, mel: np.ndarray,
                   speech: Optional[np.ndarray], style: np.ndarray, null: Optional[np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray]: ...

    def gesture(self, gesture: np.ndarray, timesteps: np.ndarray, audio: np.ndarray,
                speech: Optional[np.ndarray], expression_x0: np.ndarray, style: np.ndarray,
                null: Optional[np.ndarray], attend: Optional[np.ndarray]) -> np.ndarray: ...


@dataclass(frozen=True)
class Guidance:
    """The scales one generation samples with (None: that guidance is off)."""

    scale: Optional[float] = None   # classifier-free, both branches (the gesture branch only without skip)
    skip: Optional[float] = None    # gesture skip guidance
    style: Optional[float] = None   # style guidance of the gestures
    legs_skip: Optional[float] = None  # skip guidance of a lower branch's channels, the last `lower` (None: skip)
    lower: int = 0                  # gesture channels a lower branch makes (a whole-body model's hips and legs)

    def __post_init__(self):
        # uncond + 1 * (cond - uncond) is the conditioned pass alone: skip the null pass
        if self.scale == 1.0:
            object.__setattr__(self, "scale", None)
        if self.skip == 0.0:
            object.__setattr__(self, "skip", None)
        if self.style == 1.0:
            object.__setattr__(self, "style", None)

    def skip_scales(self, channels: int) -> Union[float, np.ndarray]:
        """The skip-guidance scale of each of `channels` gesture channels: `skip`, or per
        channel with a lower branch's last `lower` at `legs_skip`."""
        if self.legs_skip is None or not self.lower:
            return self.skip
        scales = np.full(channels, self.skip, np.float32)
        scales[channels - self.lower:] = self.legs_skip
        return scales


def _rows(values: Optional[np.ndarray], n: int) -> Optional[np.ndarray]:
    """The batch `n` times over, [a, b, a, b] (the layout the masks and the mixing assume)."""
    return None if values is None else np.concatenate([values] * n)


def classifier_free(out: np.ndarray, scale: float) -> np.ndarray:
    """u + w (c - u) over a doubled batch [null-conditioned u | conditioned c]."""
    u, c = np.split(out, 2)
    return u + np.float32(scale) * (c - u)


def skip_guided(out: np.ndarray, scale: Union[float, np.ndarray]) -> np.ndarray:
    """c + s (c - k) over a doubled batch [conditioned c | without self-attention k]; `scale`
    one number, or one per channel (`Guidance.skip_scales`)."""
    c, k = np.split(out, 2)
    return c + np.asarray(scale, np.float32) * (c - k)


def step_eps(net: Network, gesture_dim: int, x: np.ndarray, timesteps: np.ndarray, mel: np.ndarray,
             speech: Optional[np.ndarray], style: np.ndarray, x0_coefs: tuple[np.ndarray, np.ndarray],
             guidance: Guidance = Guidance(), face_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Guided noise prediction (B, L, D) for x_t (B, L, D), gesture channels first, and the
    speech features (B, L, A) the branches fused (`gesture_eps` takes them again).

    timesteps: (B,) in the 1000-step indexing; x0_coefs: sqrt(1/abar_t), sqrt(1/abar_t - 1)
    as (B, 1, 1); style: (B, S) one-hot. face_only: run the expression branch alone (it
    never sees the gestures); the gesture channels of the prediction are zero.
    """
    gesture, expression = x[..., :gesture_dim], x[..., gesture_dim:]
    eps_exp, audio = face_eps(net, expression, timesteps, mel, speech, style, guidance)
    if face_only:
        return np.concatenate([np.zeros_like(gesture), eps_exp], axis=-1), audio
    a, c = x0_coefs
    expression_x0 = (a * expression - c * eps_exp).astype(np.float32)
    eps_ges = gesture_eps(net, gesture, timesteps, audio, speech, style, expression_x0, guidance)
    return np.concatenate([eps_ges, eps_exp], axis=-1), audio


def face_eps(net: Network, expression: np.ndarray, timesteps: np.ndarray, mel: np.ndarray,
             speech: Optional[np.ndarray], style: np.ndarray, guidance: Guidance = Guidance()
             ) -> tuple[np.ndarray, np.ndarray]:
    """The expression branch's guided noise prediction (B, L, E) and the speech features
    (B, L, A) both branches fuse (those of the conditioned rows)."""
    b = expression.shape[0]
    with_null_rows = guidance.scale is not None  # classifier-free guidance: a null-condition row per row
    n = 2 if with_null_rows else 1
    null = np.repeat([True, False], b) if with_null_rows else None
    eps_exp, audio = net.expression(_rows(expression, n), _rows(timesteps, n), _rows(mel, n),
                                    _rows(speech, n), _rows(style, n), null)
    if with_null_rows:
        eps_exp, audio = classifier_free(eps_exp, guidance.scale), audio[b:]
    return eps_exp, audio


def gesture_eps(net: Network, gesture: np.ndarray, timesteps: np.ndarray, audio: np.ndarray,
                speech: Optional[np.ndarray], style: np.ndarray, expression_x0: np.ndarray,
                guidance: Guidance = Guidance()) -> np.ndarray:
    """The gesture branch's guided noise prediction (B, L, G), fed the speech features
    `audio` and the face's x0 (see `face_eps`)."""
    b = gesture.shape[0]
    if guidance.skip is not None:   # [conditioned | without self-attention]
        null, attend, mix = None, np.repeat([True, False], b), skip_guided
    elif guidance.scale is not None:  # [null | conditioned]
        null, attend, mix = np.repeat([True, False], b), None, classifier_free
    else:
        null, attend, mix = None, None, None
    n = 1 if mix is None else 2
    guided = n * b  # the rows `mix` combines; the null-style rows of style guidance follow them
    styles = _rows(style, n)
    if guidance.style is not None:  # one more group of rows: conditioned, null style
        n += 1
        styles = np.concatenate([styles, np.zeros_like(style)])
        null = None if null is None else np.concatenate([null, np.zeros(b, bool)])
        attend = None if attend is None else np.concatenate([attend, np.ones(b, bool)])
    eps_all = net.gesture(_rows(gesture, n), _rows(timesteps, n), _rows(audio, n), _rows(speech, n),
                          _rows(expression_x0, n), styles, null, attend)
    eps_ges = eps_all[:guided]
    if mix is not None:
        eps_ges = mix(eps_ges, guidance.skip_scales(eps_ges.shape[-1]) if mix is skip_guided else guidance.scale)
    if guidance.style is not None:
        conditioned = eps_all[b:2 * b] if mix is classifier_free else eps_all[:b]
        eps_ges = eps_ges + np.float32(guidance.style - 1.0) * (conditioned - eps_all[-b:])
    return eps_ges
