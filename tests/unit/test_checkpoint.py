"""Checkpoints: self-describing round trips, templates, atomic writes, corruption handling."""

from __future__ import annotations

import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import checkpoint as ckpt
from patexgs_jax import random_scene
from patexgs_jax.checkpoint import (
    CheckpointError,
    CorruptCheckpointError,
    check_writable,
    checkpoint_path,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    read_metadata,
    save_checkpoint,
)
from patexgs_jax.densify import DensifyStats
from patexgs_jax.optim import AdamState, make_optimizer


@pytest.fixture(scope="module")
def state():
    scene = random_scene(0, 5, sh_degree=1, rgb_sizes=[2, 0, 3, 1, 0], alpha_sizes=[0, 4, 0, 0, 2],
                         capacity=8)
    opt = make_optimizer(1.0).init(scene)
    rng = np.random.default_rng(7)
    rng.normal(size=3)
    return {
        "scene": scene, "opt": opt, "stats": DensifyStats.zeros(8), "rng": rng,
        "rng_state": np.random.default_rng(1).bit_generator.state, "step": 1234,
        "schedule": {"levels": [1, 2, 4], "lr": 2.5e-3, "name": "tex", "nothing": None,
                     "by_level": {3: (True, 1.5), 4: (False, 0.0)}},
        "np_scalar": np.float32(0.25), "np_array": np.arange(6, dtype=np.int16).reshape(2, 3),
        "key": jax.random.key(3), "bf16": jnp.ones(3, jnp.bfloat16),
    }


def assert_tree_equal(a, b):
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        assert type(x) is type(y) or (isinstance(x, jax.Array) and isinstance(y, jax.Array)), (x, y)
        if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            np.testing.assert_array_equal(jax.random.key_data(x), jax.random.key_data(y))
        elif hasattr(x, "dtype"):
            assert x.dtype == y.dtype and np.shape(x) == np.shape(y)
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        else:
            assert x == y


def test_round_trip_without_template(tmp_path, state):
    p = save_checkpoint(checkpoint_path(tmp_path, 10), state, {"step": 10, "psnr": np.float32(30.5)})
    tree, meta = load_checkpoint(p)
    assert meta == {"step": 10, "psnr": 30.5}
    rng = tree.pop("rng")
    orig = dict(state)
    orig_rng = orig.pop("rng")
    assert_tree_equal(tree, orig)
    assert isinstance(tree["opt"][0], AdamState)
    assert tree["scene"].rgb.channels == 3 and tree["scene"].alpha.capacities == state["scene"].alpha.capacities
    assert rng.normal() == np.random.default_rng(7).normal(size=4)[3] and orig_rng is not rng
    assert isinstance(tree["np_array"], np.ndarray) and isinstance(tree["np_scalar"], np.float32)
    assert tree["schedule"]["by_level"][3] == (True, 1.5)
    assert read_metadata(p)["step"] == 10


def test_template(tmp_path, state):
    small = {"scene": state["scene"], "opt": state["opt"], "step": 3}
    p = save_checkpoint(tmp_path / "a.ckpt", small)
    tree, _ = load_checkpoint(p, template=small)
    assert_tree_equal(tree, small)
    # After capacity growth the template no longer fits: clear error; no template still works.
    bigger = random_scene(0, 5, sh_degree=1, rgb_sizes=[2, 0, 3, 1, 0], alpha_sizes=[0, 4, 0, 0, 2],
                          capacity=16)
    tmpl = {"scene": bigger, "opt": make_optimizer(1.0).init(bigger), "step": 0}
    with pytest.raises(CheckpointError,
                       match=r"leaf \['opt'\]\[0\]\.mu\.means is an array of shape \(8, 3\).*\(16, 3\)"):
        load_checkpoint(p, template=tmpl)
    with pytest.raises(CheckpointError, match="structure"):
        load_checkpoint(p, template={"scene": state["scene"]})


def test_unsupported_and_bad_metadata(tmp_path):
    with pytest.raises(TypeError, match="cannot checkpoint"):
        save_checkpoint(tmp_path / "x.ckpt", {"f": object()})
    with pytest.raises(TypeError, match="metadata"):
        save_checkpoint(tmp_path / "x.ckpt", {}, {"bad": object()})
    assert list(tmp_path.iterdir()) == []


def test_atomic_on_crash(tmp_path, state, monkeypatch):
    tree = {"scene": state["scene"], "step": 1}
    p = save_checkpoint(tmp_path / "same.ckpt", tree, {"step": 1})
    before = p.read_bytes()

    calls = {"n": 0}
    real = ckpt.checkpoint_members.write_npy

    def crash(*a, **k):  # dies half-way through the arrays
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt("simulated crash")
        return real(*a, **k)

    monkeypatch.setattr(ckpt.checkpoint_members, "write_npy", crash)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(p, {"scene": state["scene"], "step": 2}, {"step": 2})
    monkeypatch.setattr(ckpt.checkpoint_members, "write_npy", real)
    assert p.read_bytes() == before and [f.name for f in tmp_path.iterdir()] == ["same.ckpt"]

    monkeypatch.setattr(ckpt.os, "replace", lambda *a: (_ for _ in ()).throw(OSError(28, "No space left")))
    with pytest.raises(CheckpointError, match="could not write"):
        save_checkpoint(tmp_path / "next.ckpt", tree, {"step": 2})
    monkeypatch.undo()
    assert [f.name for f in tmp_path.iterdir()] == ["same.ckpt"]

    # A hard kill leaves a hidden temp file: never picked up.
    (tmp_path / ".ckpt_000000009.ckpt.tmp-abc").write_bytes(before[: len(before) // 2])
    assert latest_checkpoint(tmp_path) == p
    assert load_checkpoint(p)[1] == {"step": 1}


@pytest.mark.parametrize("damage", ["truncate", "flip", "empty", "garbage"])
def test_corrupt_file_errors(tmp_path, state, damage):
    p = save_checkpoint(tmp_path / "c.ckpt", {"scene": state["scene"]})
    data = bytearray(p.read_bytes())
    if damage == "truncate":
        data = data[: len(data) * 2 // 3]
    elif damage == "flip":
        data[len(data) // 2] ^= 0xFF
    elif damage == "empty":
        data = b""
    else:
        data = os.urandom(500)
    p.write_bytes(bytes(data))
    with pytest.raises(CorruptCheckpointError, match="c.ckpt"):
        load_checkpoint(p)


def test_truncation_fuzz(tmp_path, state):
    p = save_checkpoint(tmp_path / "f.ckpt", {"opt": state["opt"], "k": 1})
    data = p.read_bytes()
    rng = np.random.default_rng(0)
    for cut in list(rng.integers(0, len(data), 12)) + [len(data) - 1, 22]:
        p.write_bytes(data[:cut])
        with pytest.raises(CorruptCheckpointError):
            load_checkpoint(p)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.ckpt")


def test_latest_skips_corrupt_and_keep(tmp_path, state):
    tree = {"stats": state["stats"], "step": 0}
    for step in (100, 200, 300):
        save_checkpoint(checkpoint_path(tmp_path, step), tree, {"step": step})
    newest = checkpoint_path(tmp_path, 300)
    newest.write_bytes(newest.read_bytes()[:-40])
    with pytest.warns(UserWarning, match="ckpt_000000300.ckpt"):
        got = latest_checkpoint(tmp_path)
    assert got == checkpoint_path(tmp_path, 200)
    assert latest_checkpoint(tmp_path / "nope") is None

    for step in (400, 500, 600):
        save_checkpoint(checkpoint_path(tmp_path, step), tree, {"step": step}, keep=2)
    assert [f.name for f in list_checkpoints(tmp_path)] == ["ckpt_000000500.ckpt", "ckpt_000000600.ckpt"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_metadata(latest_checkpoint(tmp_path))["step"] == 600


def test_check_writable(tmp_path, monkeypatch):
    d = check_writable(tmp_path / "new" / "dir")
    assert d.is_dir() and list(d.iterdir()) == []
    with pytest.raises(CheckpointError, match="MiB"):
        check_writable(tmp_path, required_bytes=1 << 62)
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(CheckpointError, match="file"):
        check_writable(f)

    def ro(*a, **k):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(ckpt.tempfile, "mkstemp", ro)
    with pytest.raises(CheckpointError, match="not writable.*Read-only"):
        check_writable(tmp_path)


def test_fields_added_since_take_their_defaults(tmp_path):
    """A checkpoint written before a dataclass gained a field with a default (Scene.filter3d) loads
    with the default; a stored field the class no longer has is still an error."""
    import json
    import zipfile

    path = save_checkpoint(tmp_path / "a.ckpt", random_scene(0, 5))

    def rewrite(edit):
        with zipfile.ZipFile(path) as z:
            members = {n: z.read(n) for n in z.namelist()}
        spec = json.loads(members["spec.json"])
        edit(spec["tree"]["f"])
        members["spec.json"] = json.dumps(spec).encode()
        out = tmp_path / "b.ckpt"
        with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as z:
            for n, data in members.items():
                z.writestr(n, data)
        return out

    old = rewrite(lambda f: f.pop("filter3d"))
    scene, _ = load_checkpoint(old)
    assert scene.filter3d is None and scene.num_active() == 5
    with pytest.raises(ckpt.CheckpointError, match="do not match"):
        load_checkpoint(rewrite(lambda f: f.update(gone={"t": "none"})))


def _with_spec(path, spec: dict, bad):
    """A copy of the checkpoint at ``path`` with its spec.json replaced by ``spec``, written to ``bad``."""
    import json
    import zipfile

    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    members["spec.json"] = json.dumps(spec).encode()
    with zipfile.ZipFile(bad, "w", zipfile.ZIP_STORED) as z:
        for n, data in members.items():
            z.writestr(n, data)
    return bad


def test_repeated_values_are_stored_once(tmp_path, monkeypatch):
    """An array that is bitwise one value is stored as that value and read back bitwise (signed zeros
    and NaN payloads kept; an array that varies anywhere, even past the first elements compared, or
    only from row to row, is stored whole); a version-1 file (no blocks) still reads; a block
    whose shape does not fit its array is a corrupt file."""
    import json
    import zipfile

    rows = np.arange(40, dtype=np.float32)[:, None, None, None] * np.ones((1, 3, 3, 2), np.float32)
    late = np.zeros((40, 5), np.float32)
    late[-1, -1] = 1.0  # differs only past the elements compared first
    neg = np.zeros((8, 4), np.float32)
    neg[5, 2] = -0.0
    nan = np.full(6, np.nan, np.float32)
    nan.view(np.uint32)[3] ^= 1  # another NaN payload
    tree = {"zeros": jnp.zeros((50, 7), jnp.float32), "rows": jnp.asarray(rows), "late": late, "neg": neg,
            "nan": nan, "flags": np.ones((9, 2), bool), "ints": np.full((4, 4), -3, np.int64),
            "row_ints": np.repeat(np.arange(5, dtype=np.int32)[:, None], 3, axis=1), "one": np.zeros(1, np.float32),
            "varied": np.random.default_rng(0).normal(size=(30, 4)).astype(np.float32),
            "bf16": jnp.zeros((4, 2), jnp.bfloat16)}
    path = save_checkpoint(tmp_path / "a.ckpt", tree)
    with zipfile.ZipFile(path) as z:
        spec = json.loads(z.read("spec.json"))
        stored = {k: v.get("shape") for k, v in zip(spec["tree"]["k"], spec["tree"]["v"])}
        sizes = {k: z.getinfo(f"arrays/{v['i']}.npy").file_size for k, v in zip(spec["tree"]["k"], spec["tree"]["v"])}
    assert {k for k, v in stored.items() if v} == {"zeros", "flags", "ints", "bf16"}
    assert sizes["zeros"] < 200 and sizes["rows"] > rows.nbytes
    back, _ = load_checkpoint(path)
    for k, v in tree.items():
        got = np.asarray(back[k])
        assert got.shape == np.shape(v) and got.dtype == np.asarray(v).dtype, k
        assert isinstance(back[k], jax.Array) or got.flags.writeable, k
        assert got.tobytes() == np.asarray(v).tobytes(), k
    assert isinstance(back["zeros"], jax.Array) and isinstance(back["late"], np.ndarray)

    monkeypatch.setattr(ckpt, "VERSION", 1)
    monkeypatch.setattr(ckpt, "_repeated_block", lambda arr: None)
    old, _ = load_checkpoint(save_checkpoint(tmp_path / "v1.ckpt", tree))
    assert all(np.asarray(old[k]).tobytes() == np.asarray(v).tobytes() for k, v in tree.items())
    monkeypatch.undo()

    spec["tree"]["v"][spec["tree"]["k"].index("zeros")]["shape"] = [50]
    with pytest.raises(CorruptCheckpointError, match="not a block"):
        load_checkpoint(_with_spec(path, spec, tmp_path / "bad.ckpt"))


def test_zero_rows_are_not_stored(tmp_path, monkeypatch):
    """An array with many all-zero rows (a texture bucket's free slots) is stored without them and
    read back bitwise (a row holding only -0.0 is not zero, nor one whose first element only is); one
    with few zero rows is stored whole;
    a row mask that does not fit its rows is a corrupt file."""
    import json
    import zipfile

    from patexgs_jax import checkpoint_rows

    monkeypatch.setattr(checkpoint_rows, "MIN_BYTES", 1024)
    rng = np.random.default_rng(0)
    bucket = rng.normal(size=(300, 4, 4, 3)).astype(np.float32)
    bucket[rng.random(300) < 0.4] = 0.0
    bucket[7] = -0.0
    bucket[11] = 1.0
    bucket[11, 0, 0, 0] = 0.0  # a row whose first element is zero, the rest not
    few = rng.normal(size=(300, 8)).astype(np.float32)
    few[:10] = 0.0
    runs = np.zeros((300, 32, 32, 1), np.float32)  # long runs of kept rows (slots filled from the first)
    runs[:180] = rng.normal(size=(180, 32, 32, 1))
    runs[190:200] = 1.0
    tree = {"bucket": jnp.asarray(bucket), "host": bucket.copy(), "few": few, "ints": (bucket != 0).astype(np.int16),
            "runs": jnp.asarray(runs)}
    path = save_checkpoint(tmp_path / "z.ckpt", tree)
    with zipfile.ZipFile(path) as z:
        spec = json.loads(z.read("spec.json"))
        nodes = dict(zip(spec["tree"]["k"], spec["tree"]["v"]))
        size = {k: z.getinfo(f"arrays/{v['i']}.npy").file_size for k, v in nodes.items()}
    assert {k for k, v in nodes.items() if "rows" in v} == {"bucket", "host", "ints", "runs"}
    assert size["bucket"] < 0.7 * bucket.nbytes and size["few"] > few.nbytes
    back, _ = load_checkpoint(path)
    for k, v in tree.items():
        got = np.asarray(back[k])
        assert got.dtype == np.asarray(v).dtype and got.tobytes() == np.asarray(v).tobytes(), k
    assert isinstance(back["bucket"], jax.Array) and np.asarray(back["host"]).flags.writeable

    nodes["bucket"]["rows"] = nodes["ints"]["i"]  # another member as the mask: it does not fit
    with pytest.raises(CorruptCheckpointError, match="flagged rows"):
        load_checkpoint(_with_spec(path, spec, tmp_path / "bad.ckpt"))
