"""LPIPS v0.1 (Zhang et al. 2018) in pure JAX, AlexNet and VGG16 trunks; an optional metric.

The network, for inputs ``x, y`` in ``[0, 1]`` of shape ``(H, W, 3)`` or ``(B, H, W, 3)``:

1. ``x -> 2 x - 1`` (LPIPS works on ``[-1, 1]``), then LPIPS's scaling layer
   ``(x - SHIFT) / SCALE`` per channel;
2. the backbone's feature taps (torchvision's ``features`` layers, unchanged):

   - ``alex``: conv 11x11/4 pad 2 (3->64) relu [tap] - maxpool 3/2 - conv 5x5 pad 2 (64->192) relu [tap]
     - maxpool 3/2 - conv 3x3 pad 1 (192->384) relu [tap] - conv 3x3 (384->256) relu [tap]
     - conv 3x3 (256->256) relu [tap];
   - ``vgg`` (VGG16): 3x3 pad 1 convs, 2x2/2 max-pools; taps relu1_2, relu2_2, relu3_3, relu4_3,
     relu5_3 (64, 128, 256, 512, 512 channels);

3. per tap and pixel, unit normalisation over channels ``f / (||f||_2 + 1e-10)``;
4. squared difference of the normalised features, the learned 1x1 "lin" layer (a non-negative
   weight per channel, no bias), mean over pixels, sum over the five taps.

3DGS reports LPIPS with the VGG trunk; the LPIPS authors recommend AlexNet as a forward metric.

Weights (a pytree of numpy/jax arrays, never downloaded here)
--------------------------------------------------------------
In memory, ``params = {"convs": [{"w": (kh, kw, cin, cout), "b": (cout,)}, ...], "lins": [(c,), ...]}``
(conv kernels HWIO, for ``lax.conv_general_dilated`` with NHWC images; 5 convs for alex, 13 for vgg,
so the trunk is known from the structure and :func:`lpips` needs no static argument).

On disk: one ``.npz`` per trunk, named ``lpips_alex.npz`` / ``lpips_vgg.npz``, with float32 arrays

* ``{net}/conv{i}/w``: kernel of the i-th conv of the trunk, **HWIO** ``(kh, kw, cin, cout)``
  (torch's OIHW transposed by ``(2, 3, 1, 0)``), ``i = 0 ... 4`` (alex) or ``0 ... 12`` (vgg);
* ``{net}/conv{i}/b``: its bias ``(cout,)``;
* ``{net}/lin{k}/w``: the k-th lin layer's weights ``(c_k,)``, ``k = 0 ... 4``.

:func:`load_lpips` looks for the file at the path given, else in the directory named by the
environment variable ``PATEXGS_LPIPS_WEIGHTS``, else in ``~/.cache/patexgs_jax/lpips/``, and raises
:class:`LPIPSWeightsUnavailable` if there is none. The files are made from the ``lpips`` package's
pretrained model by ``experiments/convert_lpips_weights.py`` (needs torch, torchvision, lpips and
internet access, once, on any machine).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = [
    "NETS",
    "SHIFT",
    "SCALE",
    "ENV_VAR",
    "ConvSpec",
    "ARCHITECTURES",
    "LIN_CHANNELS",
    "LPIPSWeightsUnavailable",
    "weights_filename",
    "default_cache_dir",
    "find_lpips_weights",
    "lpips_available",
    "load_lpips",
    "save_lpips",
    "params_to_arrays",
    "params_from_arrays",
    "random_lpips_params",
    "lpips",
]

NETS = ("alex", "vgg")
ENV_VAR = "PATEXGS_LPIPS_WEIGHTS"

# LPIPS v0.1 scaling layer: applied to inputs in [-1, 1] as (x - SHIFT) / SCALE.
SHIFT = np.array([-0.030, -0.088, -0.188], dtype=np.float32)
SCALE = np.array([0.458, 0.448, 0.450], dtype=np.float32)

_NORM_EPS = 1e-10


@dataclasses.dataclass(frozen=True)
class ConvSpec:
    """One conv + relu of a trunk, with an optional max-pool before it and a feature tap after it."""

    kernel: int
    stride: int
    pad: int
    cin: int
    cout: int
    pool_before: tuple[int, int] | None = None  # (window, stride), no padding, floor mode
    tap: bool = False


def _vgg16() -> tuple[ConvSpec, ...]:
    blocks = [(3, 64, 2), (64, 128, 2), (128, 256, 3), (256, 512, 3), (512, 512, 3)]
    specs = []
    for b, (cin, cout, n) in enumerate(blocks):
        for j in range(n):
            specs.append(
                ConvSpec(3, 1, 1, cin if j == 0 else cout, cout,
                         pool_before=(2, 2) if (b > 0 and j == 0) else None, tap=(j == n - 1))
            )
    return tuple(specs)


ARCHITECTURES: dict[str, tuple[ConvSpec, ...]] = {
    "alex": (
        ConvSpec(11, 4, 2, 3, 64, tap=True),
        ConvSpec(5, 1, 2, 64, 192, pool_before=(3, 2), tap=True),
        ConvSpec(3, 1, 1, 192, 384, pool_before=(3, 2), tap=True),
        ConvSpec(3, 1, 1, 384, 256, tap=True),
        ConvSpec(3, 1, 1, 256, 256, tap=True),
    ),
    "vgg": _vgg16(),
}
LIN_CHANNELS = {net: tuple(s.cout for s in specs if s.tap) for net, specs in ARCHITECTURES.items()}


class LPIPSWeightsUnavailable(RuntimeError):
    """The LPIPS weight file is not on this machine (see the message for how to make it)."""


def _check_net(net: str) -> str:
    if net == "vgg16":
        net = "vgg"
    if net not in NETS:
        raise ValueError(f"LPIPS net must be one of {NETS}, got {net!r}.")
    return net


def weights_filename(net: str) -> str:
    """``lpips_alex.npz`` or ``lpips_vgg.npz``."""
    return f"lpips_{_check_net(net)}.npz"


def default_cache_dir() -> Path:
    """``~/.cache/patexgs_jax/lpips``."""
    return Path.home() / ".cache" / "patexgs_jax" / "lpips"


def _candidates(net: str, weights) -> list[Path]:
    name = weights_filename(net)
    if weights is not None:
        p = Path(weights).expanduser()
        return [p / name if p.is_dir() else p]
    out = []
    env = os.environ.get(ENV_VAR)
    if env:
        out.append(Path(env).expanduser() / name)
    out.append(default_cache_dir() / name)
    return out


def find_lpips_weights(net: str = "alex", weights=None) -> Path | None:
    """The weight file :func:`load_lpips` would read, or None.

    ``weights``: a file, or a directory holding ``lpips_{net}.npz``; if given, nothing else is searched.
    """
    for p in _candidates(net, weights):
        if p.is_file():
            return p
    return None


def lpips_available(net: str = "alex", weights=None) -> bool:
    """Whether a weight file for ``net`` exists (evaluation records ``lpips = null`` otherwise)."""
    return find_lpips_weights(net, weights) is not None


def _unavailable_message(net: str, searched: list[Path]) -> str:
    name = weights_filename(net)
    return (
        f"LPIPS-{net} weights not found (looked for: {', '.join(str(p) for p in searched)}). "
        "The pretrained weights cannot be downloaded by this package. To make them, on a machine "
        "with internet access run, from the patexgs-jax repository root:\n"
        "    pip install torch torchvision lpips\n"
        "    python -m experiments.convert_lpips_weights --out DIR\n"
        f"then copy DIR/{name} to {default_cache_dir()}/, or set {ENV_VAR}=DIR, or pass "
        "weights=PATH to load_lpips."
    )


def params_from_arrays(arrays: Mapping[str, np.ndarray], net: str) -> dict:
    """Builds the params pytree from the npz naming (``{net}/conv{i}/w`` ...), checking every shape."""
    net = _check_net(net)
    specs = ARCHITECTURES[net]

    def get(key, shape):
        if key not in arrays:
            raise ValueError(f"LPIPS-{net} weights lack the array {key!r}.")
        a = np.asarray(arrays[key], dtype=np.float32)
        if a.shape != shape:
            raise ValueError(f"LPIPS-{net} array {key!r} has shape {a.shape}, expected {shape}.")
        return a

    convs = [
        {"w": get(f"{net}/conv{i}/w", (s.kernel, s.kernel, s.cin, s.cout)), "b": get(f"{net}/conv{i}/b", (s.cout,))}
        for i, s in enumerate(specs)
    ]
    lins = [get(f"{net}/lin{k}/w", (c,)) for k, c in enumerate(LIN_CHANNELS[net])]
    if any(np.any(w < 0) for w in lins):
        raise ValueError(f"LPIPS-{net} lin weights must be non-negative (LPIPS clamps them in training).")
    return {"convs": convs, "lins": lins}


def params_to_arrays(params: Mapping, net: str) -> dict[str, np.ndarray]:
    """The inverse of :func:`params_from_arrays`: the ``{name: float32 array}`` dict saved in the npz."""
    net = _check_net(net)
    out = {}
    for i, c in enumerate(params["convs"]):
        out[f"{net}/conv{i}/w"] = np.asarray(c["w"], dtype=np.float32)
        out[f"{net}/conv{i}/b"] = np.asarray(c["b"], dtype=np.float32)
    for k, w in enumerate(params["lins"]):
        out[f"{net}/lin{k}/w"] = np.asarray(w, dtype=np.float32)
    params_from_arrays(out, net)  # validate before anything is written
    return out


def save_lpips(path, params: Mapping, net: str) -> Path:
    """Writes ``params`` in the npz format above. ``path``: a file, or a directory (gets ``lpips_{net}.npz``)."""
    path = Path(path)
    if path.is_dir():
        path = path / weights_filename(net)
    arrays = params_to_arrays(params, net)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def load_lpips(net: str = "alex", weights=None) -> dict:
    """Loads LPIPS-``net`` weights (see the module docstring for where they are looked for).

    Raises:
      LPIPSWeightsUnavailable: no weight file; the message says how to make one.
      ValueError: the file does not hold LPIPS-``net`` weights in this package's format.
    """
    net = _check_net(net)
    path = find_lpips_weights(net, weights)
    if path is None:
        raise LPIPSWeightsUnavailable(_unavailable_message(net, _candidates(net, weights)))
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    return params_from_arrays(arrays, net)


def random_lpips_params(net: str = "alex", seed: int = 0) -> dict:
    """Random weights with the trunk's shapes (He-normal kernels, small biases, lin weights in [0, 1)).

    For tests and smoke runs only: the values mean nothing perceptually.
    """
    net = _check_net(net)
    rng = np.random.default_rng(seed)
    convs = []
    for s in ARCHITECTURES[net]:
        fan_in = s.kernel * s.kernel * s.cin
        w = rng.standard_normal((s.kernel, s.kernel, s.cin, s.cout)) * np.sqrt(2.0 / fan_in)
        b = 0.1 * rng.standard_normal(s.cout)
        convs.append({"w": w.astype(np.float32), "b": b.astype(np.float32)})
    lins = [rng.random(c).astype(np.float32) for c in LIN_CHANNELS[net]]
    return {"convs": convs, "lins": lins}


def _net_of(params) -> str:
    n = len(params["convs"])
    for net, specs in ARCHITECTURES.items():
        if len(specs) == n:
            return net
    raise ValueError(f"LPIPS params have {n} convs; expected 5 (alex) or 13 (vgg).")


def _max_pool(x, window: int, stride: int):
    return lax.reduce_window(
        x, -jnp.inf, lax.max, (1, window, window, 1), (1, stride, stride, 1), "VALID"
    )


def _check_not_empty(x, net: str) -> None:
    if x.shape[1] < 1 or x.shape[2] < 1:
        raise ValueError(f"Images too small for LPIPS-{net}: a feature map became {x.shape[1]}x{x.shape[2]}.")


def _features(params, x, net: str) -> list[jax.Array]:
    """The trunk's tapped relu outputs for an NHWC batch."""
    taps = []
    for s, c in zip(ARCHITECTURES[net], params["convs"]):
        if s.pool_before is not None:
            x = _max_pool(x, *s.pool_before)
        _check_not_empty(x, net)
        x = lax.conv_general_dilated(
            x, jnp.asarray(c["w"], x.dtype), (s.stride, s.stride), [(s.pad, s.pad)] * 2,
            dimension_numbers=("NHWC", "HWIO", "NHWC"), precision=lax.Precision.HIGHEST,
        )
        _check_not_empty(x, net)
        x = jax.nn.relu(x + jnp.asarray(c["b"], x.dtype))
        if s.tap:
            taps.append(x)
    return taps


def _unit_normalize(f):
    """``f / (||f|| + eps)`` over channels, with a finite gradient where ``f`` is all zero."""
    sq = jnp.sum(f * f, axis=-1, keepdims=True)
    pos = sq > 0
    norm = jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)
    return f / (norm + _NORM_EPS)


@jax.jit
def lpips(img, ref, params) -> jax.Array:
    """LPIPS v0.1 distance between images in ``[0, 1]`` (jitted; differentiable).

    Args:
      img, ref: ``(H, W, 3)`` or ``(B, H, W, 3)`` arrays of the same shape, in ``[0, 1]``
        (at least 31x31 for alex, 16x16 for vgg).
      params: from :func:`load_lpips` (or :func:`random_lpips_params`); the trunk is inferred from it.

    Returns:
      A float32 scalar for one image pair, shape ``(B,)`` for a batch (``float(...)`` for a Python
      number). Non-negative, symmetric, zero for identical images.
    """
    net = _net_of(params)
    img = jnp.asarray(img, jnp.float32)
    ref = jnp.asarray(ref, jnp.float32)
    if img.shape != ref.shape or img.ndim not in (3, 4) or img.shape[-1] != 3:
        raise ValueError(f"lpips needs two (H, W, 3) or (B, H, W, 3) arrays of one shape, got {img.shape}, {ref.shape}.")
    single = img.ndim == 3
    if single:
        img, ref = img[None], ref[None]
    # Two trunk passes rather than one on the concatenated batch, so that equal inputs go through
    # identical computations (lpips(x, x) is exactly 0).
    feats_img = _features(params, (img * 2.0 - 1.0 - SHIFT) / SCALE, net)
    feats_ref = _features(params, (ref * 2.0 - 1.0 - SHIFT) / SCALE, net)
    total = jnp.zeros((img.shape[0],), jnp.float32)
    for f0, f1, w in zip(feats_img, feats_ref, params["lins"]):
        d = (_unit_normalize(f0) - _unit_normalize(f1)) ** 2
        # Where the features are equal the distance is exactly 0; without this, the channel-norm
        # reductions of the two sides may round differently (XLA CPU) and leave ~1e-15.
        d = jnp.where(jnp.all(f0 == f1, axis=-1, keepdims=True), 0.0, d)
        per_pixel = jnp.dot(d, jnp.asarray(w, jnp.float32), precision=lax.Precision.HIGHEST)
        total = total + jnp.mean(per_pixel, axis=(1, 2))
    return total[0] if single else total
