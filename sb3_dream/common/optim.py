"""The optimizer arguments the policies share."""

from typing import Any, Dict, Type

import torch as th


def default_optimizer_kwargs(
    optimizer_class: Type[th.optim.Optimizer], optimizer_kwargs: Dict[str, Any]
) -> Dict[str, Any]:
    """``optimizer_kwargs`` with ``fused=True`` added for :class:`torch.optim.Adam` unless they set
    ``fused`` or ``foreach`` themselves (then, and for any other optimizer, unchanged).

    Adam's fused kernel is the paper's Adam in one call per step instead of about 25 small ones per
    parameter tensor (rounded differently from torch's per-parameter loop); the policies here have
    many small tensors, where the loop's calls cost more than its arithmetic.
    ``optimizer_kwargs=dict(fused=False)`` gives the loop back.
    """
    if optimizer_class is th.optim.Adam and not {"fused", "foreach"} & set(optimizer_kwargs):
        return {**optimizer_kwargs, "fused": True}
    return dict(optimizer_kwargs)
