r"""An exponential moving average of a network's weights (Polyak averaging): after every optimiser
step

.. math::
    \bar w \leftarrow d\, \bar w + (1 - d)\, w ,

an average over about :math:`1 / (1 - d)` steps. Buffers (the normaliser's statistics) are not
averaged.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import Tensor, nn


class WeightAverage:
    r"""The running average :math:`\bar w` of ``module``'s parameters at rate ``decay``, starting at
    them: :meth:`update` after each optimiser step, :meth:`applied` swaps it in for a block,
    :meth:`state_dict` / :meth:`load_state_dict` keep it in a checkpoint.

    Args:
        module: the network; its parameters are replaced only inside :meth:`applied`.
        decay: :math:`d`, in ``(0, 1)``.
    """

    def __init__(self, module: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"WeightAverage: decay must be in (0, 1), got {decay}")
        self.module, self.decay = module, float(decay)
        self.average = {name: p.detach().clone() for name, p in module.named_parameters()}

    @torch.no_grad()
    def update(self) -> None:
        """:math:`\\bar w \\leftarrow d \\bar w + (1 - d) w` for every parameter."""
        for name, p in self.module.named_parameters():
            self.average[name].lerp_(p.detach(), 1.0 - self.decay)

    def state_dict(self) -> dict[str, Tensor]:
        """The averages by parameter name (copies)."""
        return {name: value.clone() for name, value in self.average.items()}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        """Continue from ``state`` (from :meth:`state_dict` of the same network); a missing,
        extra or differently shaped entry is a ValueError naming it."""
        names = set(self.average)
        if set(state) != names:
            odd = sorted(names.symmetric_difference(state))
            raise ValueError(f"WeightAverage: the saved average does not fit this network ({', '.join(odd[:3])})")
        for name, value in state.items():
            if value.shape != self.average[name].shape:
                raise ValueError(f"WeightAverage: {name} is {tuple(value.shape)} in the saved average, "
                                 f"{tuple(self.average[name].shape)} here")
            self.average[name].copy_(value)

    @contextmanager
    def applied(self) -> Iterator[nn.Module]:
        """Inside the block the module holds the averaged weights; after it, the trained ones
        again, bit for bit (also when the block raises)."""
        params = dict(self.module.named_parameters())
        trained = {name: p.detach().clone() for name, p in params.items()}
        with torch.no_grad():
            for name, p in params.items():
                p.copy_(self.average[name])
        try:
            yield self.module
        finally:
            with torch.no_grad():
                for name, p in params.items():
                    p.copy_(trained[name])
