"""Guidance distillation: a student whose one unguided pass gives its teacher's guided step.

A guided step of the fast sampling runs each branch twice: the face with and without its
speech (classifier-free guidance), the gestures with and without self-attention (skip
guidance). On one CPU core onnxruntime is compute-bound, so those batches of two cost 1.7x a
batch of one. Distilled at the scales the fast sampling uses (stage one of Meng et al. 2023,
"On distillation of guided diffusion models", at fixed scales), the student makes the same
step in one pass: `pipeline.make_plan` samples with it whenever a job asks for exactly that.

What it learns, on clips of the training data noised to each of the fast sampling's steps,
is the teacher's guided noise exactly as the sampler mixes it (`guidance.step_eps`): the face
at the model's classifier-free scale; the gestures at its skip scale, fed the guided face's
x0; and the refining pass at its own scale (skip x refine_skip). The refining pass runs at the
lowest step's noise level, so the student is told it apart by its timestep plus
REFINE_OFFSET, a timestep the schedule never reaches (`pipeline.make_eps_fn_factory` feeds it
so): taught the pass's stronger guidance at the step's own timestep, a student steered every
window's gestures twice at that strength, and they moved 5-8 % faster and jittered more.
The loss (`train.distill_loss`, beside the paper's) is the squared error of each branch's
noise, plus that of x0 and of its acceleration, weighted by abar (the low-noise steps finish
the motion).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..checkpoints import ModelBundle
from ..errors import DiffshegError
from ..foppas import FAST_TIMESTEPS, fast_sampling


REFINE_OFFSET = 1000  # added to the refining pass's timestep for a student (the schedule's run 0-999)


@dataclass(frozen=True)
class Distillation:
    """The guided sampling a student reproduces: scales and the model timesteps it steps at."""

    guidance: float
    skip: float
    refine_skip: float
    timesteps: tuple[int, ...] = FAST_TIMESTEPS
    refine_timestep: int | None = FAST_TIMESTEPS[0]  # the noise level the refining pass runs at (None: no pass)

    @classmethod
    def of(cls, teacher: ModelBundle) -> "Distillation":
        """The fast sampling of `teacher` at its default scales; refuses an unguided model."""
        if teacher.guidance is None or teacher.skip_guidance is None or not teacher.config.classifier_free:
            raise DiffshegError(f"{teacher.source}: distilling needs a model guided by default (classifier-free "
                                "and skip guidance scales in its file): there is nothing to distil from an "
                                "unguided one")
        fast = fast_sampling(teacher.sampling)
        return cls(guidance=float(teacher.guidance), skip=float(teacher.skip_guidance),
                   refine_skip=float(fast.refine_skip), timesteps=tuple(fast.timesteps),
                   refine_timestep=fast.timesteps[fast.refine] if fast.refine is not None else None)

    def record(self, teacher: ModelBundle, steps: int) -> dict:
        """What the student's file says it was distilled from and at (info["distilled"])."""
        return {"from": teacher.model_id, "guidance": self.guidance, "skip_guidance": self.skip,
                "refine_skip": self.refine_skip, "timesteps": list(self.timesteps),
                "refine_offset": REFINE_OFFSET, "steps": steps}


@torch.no_grad()
def guided_target(teacher: torch.nn.Module, d: Distillation, x_t: torch.Tensor, timesteps: torch.Tensor,
                  skip: torch.Tensor, mel: torch.Tensor, speech: torch.Tensor | None, style: torch.Tensor,
                  x0_coefs: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """The teacher's guided noise prediction (B, L, D) as the fast sampler mixes it, at the
    gestures' skip scale of each row (B,), and the guided face's x0 (B, L, E) the gestures were fed."""
    b, g = x_t.shape[0], teacher.cfg.gesture_dim
    gesture, expression = x_t[..., :g], x_t[..., g:]
    two = (lambda v: None if v is None else torch.cat([v, v]))
    first = torch.arange(2 * b, device=x_t.device) < b
    out, audio = teacher.expression(two(expression), two(timesteps), two(mel), two(speech), two(style), first)
    eps_face = out[:b] + d.guidance * (out[b:] - out[:b])  # null rows first, then conditioned
    a, c = x0_coefs
    face_x0 = a * expression - c * eps_face
    out = teacher.gesture(two(gesture), two(timesteps), two(audio[b:]), two(speech), two(face_x0), two(style),
                          None, first)  # rows with self-attention first, then without
    eps_gesture = out[:b] + skip.to(out.dtype).view(-1, 1, 1) * (out[:b] - out[b:])
    return torch.cat([eps_gesture, eps_face], dim=-1), face_x0
