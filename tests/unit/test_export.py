"""PLY export / import: exact round trips, the 2DGS and 3DGS header layouts, Mip-Splatting's baked
3D filter, and damaged files."""

from __future__ import annotations

import numpy as np
import pytest

from patexgs_jax import random_scene
from patexgs_jax.export import PlyFormatError, export_ply, load_ply, sidecar_path

RGB = [2, 0, 3, 1, 0, 5, 4]
ALPHA = [0, 4, 0, 1, 2, 0, 3]


def make_scene(sh_degree, textured, capacity=9, seed=0):
    s = random_scene(seed, 7, sh_degree=sh_degree, rgb_sizes=RGB if textured else None,
                     alpha_sizes=ALPHA if textured else None, capacity=capacity)
    act = np.asarray(s.active).copy()
    act[2] = 0.0          # an inactive slot in the middle is skipped
    return s.replace(active=act)


def expected_properties(K):
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * (K - 1))]
            + ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"])


def header_of(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode("ascii").splitlines(), data[end:]


@pytest.mark.parametrize("sh_degree,textured", [(0, False), (3, False), (0, True), (3, True)])
def test_round_trip(tmp_path, sh_degree, textured):
    scene = make_scene(sh_degree, textured)
    path = export_ply(scene, tmp_path / "scene.ply")
    assert sidecar_path(path).name == "scene.textures.npz"
    assert sidecar_path(path).exists() == textured  # (no sidecar without textures)
    back = load_ply(path)
    rows = np.flatnonzero(np.asarray(scene.active) > 0)
    assert back.capacity == rows.size == back.num_active()
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(np.asarray(getattr(back, f)), np.asarray(getattr(scene, f))[rows])
    for name in ("rgb", "alpha"):
        b0, b1 = getattr(scene, name), getattr(back, name)
        assert (b0 is None) == (b1 is None)
        if b0 is None:
            continue
        assert b1.num_buckets == b0.num_buckets and b1.channels == b0.channels
        for j, i in enumerate(rows):
            t0, t1 = b0.texture(int(i)), b1.texture(j)
            assert (t0 is None and t1 is None) or np.array_equal(t0, t1)
    big = load_ply(path, capacity=12)
    assert big.capacity == 12 and big.num_active() == rows.size
    assert float(big.opacity_logits[-1]) == -20.0
    np.testing.assert_array_equal(np.asarray(big.quats[-1]), [1, 0, 0, 0])


def test_header_layout_and_channel_major_rest(tmp_path):
    scene = make_scene(3, False)
    K = 16
    sh = np.zeros((9, K, 3), np.float32)
    sh[:] = np.arange(K)[None, :, None] * 10 + np.arange(3)[None, None, :]    # value 10 k + c
    scene = scene.replace(sh=sh)
    path = export_ply(scene, tmp_path / "s.ply")
    lines, body = header_of(path)
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    assert "element vertex 6" in lines and lines[-1] == "end_header"
    props = [ln.split() for ln in lines if ln.startswith("property")]
    assert all(p[1] == "float" for p in props)
    names = [p[2] for p in props]
    assert names == expected_properties(K) and len(names) == 61
    v = np.frombuffer(body, "<f4").reshape(6, 61)
    np.testing.assert_array_equal(v[:, 3:6], 0)                                # normals
    np.testing.assert_array_equal(v[0, 6:9], [0, 1, 2])                        # f_dc = sh[:, 0, c]
    rest = v[0, 9:54]
    for c in range(3):
        np.testing.assert_array_equal(rest[c * 15:(c + 1) * 15], np.arange(1, 16) * 10 + c)
    rows = np.flatnonzero(np.asarray(scene.active) > 0)
    np.testing.assert_array_equal(v[:, 54], np.asarray(scene.opacity_logits)[rows])
    np.testing.assert_array_equal(v[:, 55:57], np.asarray(scene.log_scales)[rows])
    np.testing.assert_array_equal(v[:, 57:61], np.asarray(scene.quats)[rows])


def write_ply(path, names, rows, extra=b""):
    head = ("ply\nformat binary_little_endian 1.0\n" f"element vertex {len(rows)}\n"
            + "".join(f"property float {n}\n" for n in names) + "end_header\n").encode()
    path.write_bytes(head + np.asarray(rows, "<f4").tobytes() + extra)


def test_foreign_and_invalid_layouts(tmp_path):
    names = expected_properties(1)
    vals = np.zeros((2, len(names)), np.float32)
    vals[:, names.index("rot_0")] = 1.0
    p = tmp_path / "plain.ply"
    write_ply(p, names, vals)
    s = load_ply(p)                                   # a plain 2DGS file without sidecar
    assert s.num_active() == 2 and s.rgb is None and s.sh.shape == (2, 1, 3)
    # (write the file, the error it gets)
    cases = [
        (lambda: write_ply(p, [n for n in names if n != "rot_3"], vals[:, :-1]), "missing vertex properties.*rot_3"),
        (lambda: write_ply(p, names + ["f_rest_0"], np.zeros((2, len(names) + 1))), "f_rest"),
        (lambda: write_ply(p, names, vals, extra=b"junk"), "unexpected bytes"),
        (lambda: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n"),
         "binary_little_endian"),
        (lambda: p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\n"
                               b"property float x\nend_header\n"), "truncated"),
    ]
    for write, match in cases:
        write()
        with pytest.raises(PlyFormatError, match=match):
            load_ply(p)


def test_sidecar_errors(tmp_path):
    scene = make_scene(1, True)
    path = export_ply(scene, tmp_path / "t.ply")
    sc = sidecar_path(path)
    good = dict(np.load(sc))
    for key, value, msg in [("version", np.asarray(2), "version 2"),
                            ("format", np.asarray("other"), "not a patexgs"),
                            ("num_gaussians", np.asarray(3), "does not belong"),
                            ("rgb_texels", good["rgb_texels"][:-1], "rgb_texels has shape")]:
        np.savez(sc, **{**good, key: value})
        with pytest.raises(PlyFormatError, match=msg):
            load_ply(path)
    np.savez(sc, **{k: v for k, v in good.items() if k != "alpha_sizes"})
    with pytest.raises(PlyFormatError, match="alpha_sizes"):
        load_ply(path)
    # A stale sidecar of another export is rejected (vertex-data checksum).
    export_ply(make_scene(1, True, seed=1), tmp_path / "other.ply")
    sc.write_bytes(sidecar_path(tmp_path / "other.ply").read_bytes())
    with pytest.raises(PlyFormatError, match="does not belong"):
        load_ply(path)


def test_fuzz_truncation_and_corruption(tmp_path):
    scene = make_scene(1, True)
    path = export_ply(scene, tmp_path / "f.ply")
    sc = sidecar_path(path)
    ply, side = path.read_bytes(), sc.read_bytes()
    rng = np.random.default_rng(0)
    header_len = ply.index(b"end_header") + 11
    cuts = [0, 3, header_len // 2, header_len - 1, header_len, header_len + 5, len(ply) - 1]
    for cut in cuts + list(rng.integers(0, len(ply), 8)):
        path.write_bytes(ply[:cut])
        with pytest.raises(PlyFormatError):
            load_ply(path)
    # Random byte corruption anywhere in the PLY: an error (or, in a comment, a correct load).
    for _ in range(25):
        data = bytearray(ply)
        pos = int(rng.integers(0, len(data)))
        data[pos] = (data[pos] + int(rng.integers(1, 256))) % 256
        path.write_bytes(bytes(data))
        try:
            s = load_ply(path)
        except PlyFormatError:
            continue
        np.testing.assert_array_equal(np.asarray(s.means), np.asarray(load_ply_ok(ply, tmp_path).means))
    path.write_bytes(ply)
    for cut in [0, 10, len(side) // 2, len(side) - 1]:
        sc.write_bytes(side[:cut])
        with pytest.raises(PlyFormatError, match="sidecar"):
            load_ply(path)


def load_ply_ok(ply_bytes, tmp_path):
    p = tmp_path / "ok.ply"
    p.write_bytes(ply_bytes)
    return load_ply(p)


def test_3dgs_layout_round_trip_and_baked_filter(tmp_path):
    """A 3D scene is written in 3DGS's layout (three scales, the order 3DGS's viewers read), read back
    exactly; with Mip-Splatting's 3D filter the file holds the filtered scales and opacities, whose
    render (no filter) equals the filtered scene's."""
    import jax.numpy as jnp

    from patexgs_jax import Capacity, RenderConfig, look_at, render_jit
    from patexgs_jax.camera import Camera

    scene = random_scene(3, 7, sh_degree=1, capacity=9, scale_dims=3, scale_range=(0.15, 0.5))
    act = np.asarray(scene.active).copy()
    act[2] = 0.0
    scene = scene.replace(active=act)
    path = export_ply(scene, tmp_path / "g3.ply")
    lines, body = header_of(path)
    assert [ln.split()[-1] for ln in lines if ln.startswith("property")] == (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    rows = np.frombuffer(body, "<f4").reshape(6, 26)   # read back by hand: the 3DGS vertex layout
    keep = np.asarray(act[:7]) > 0
    for cols, name in ((slice(0, 3), "means"), (slice(18, 19), "opacity_logits"), (slice(19, 22), "log_scales"),
                       (slice(22, 26), "quats")):
        np.testing.assert_array_equal(rows[:, cols], np.asarray(getattr(scene, name))[:7][keep].reshape(6, -1))
    back = load_ply(path)
    assert back.is_3d and back.filter3d is None and back.rgb is None
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name))[:6], np.asarray(getattr(scene, name))[:7][keep])

    f = np.full(9, 0.05 ** 2, np.float32)
    filtered = scene.replace(filter3d=jnp.asarray(f))
    back = load_ply(export_ply(filtered, tmp_path / "mip.ply"), capacity=9)
    cam = Camera.from_intrinsics([40.0, 40.0, 22.0, 18.0], look_at((0.3, -0.4, -2.6), (0.0, 0.0, 0.0)), 44, 36)
    cfg = RenderConfig(mip="none", coverage="prefilter")
    ref = render_jit(filtered, cam, config=cfg, capacity=Capacity(4096))
    out = render_jit(back, cam, config=cfg, capacity=Capacity(4096))
    assert float(jnp.mean(ref.alpha)) > 0.05
    np.testing.assert_allclose(np.asarray(out.rgb), np.asarray(ref.rgb), atol=2e-5, rtol=0)
