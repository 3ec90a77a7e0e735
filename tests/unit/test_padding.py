"""Training padding policies (patexgs_jax.padding.TrainPadding): which policy "auto" picks, the one
size every view fits, and the tile capacity's growth rule (headroom over the pairs a view needs)."""

from __future__ import annotations

import numpy as np
import pytest

from patexgs_jax import Camera, padding
from patexgs_jax.render import Capacity


def _cam(w, h):
    return Camera(K=np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]], np.float32),
                  world_to_camera=np.eye(4, dtype=np.float32), width=w, height=h)


CAMS = [_cam(48, 32), _cam(45, 30), _cam(48, 40), _cam(40, 36)]


def test_auto_is_one_on_accelerators_and_per_size_on_cpu():
    assert padding.resolve_padding("auto", "cpu") == "per-size"
    assert padding.resolve_padding("auto", "gpu") == padding.resolve_padding("auto", "tpu") == "one"
    assert padding.resolve_padding("per-size", "gpu") == "per-size"
    with pytest.raises(ValueError, match="padding must be one of"):
        padding.resolve_padding("largest")


def test_one_size_fits_every_view():
    pad = padding.TrainPadding("one", CAMS)
    assert pad.size() == padding.one_size(CAMS) == (48, 48)
    for c in CAMS:
        cam = pad.camera(c)
        assert (cam.height, cam.width) == (48, 48)
        np.testing.assert_array_equal(np.asarray(cam.K), np.asarray(c.K))
    assert padding.TrainPadding("per-size", CAMS).camera(CAMS[1]).height == 32
    with pytest.raises(ValueError, match="does not fit the padded size"):
        padding.train_camera(_cam(64, 32), 16, (48, 48))
    share = padding.extra_pixel_share(CAMS)
    assert share["sizes"] == 2 and share["one_size"] == [48, 48]
    assert share["one_over_per_size"] == pytest.approx(4 * 48 * 48 / (2 * 48 * 32 + 2 * 48 * 48) - 1)


@pytest.mark.parametrize("needed", [1, 900, 1025, 3000, 4096, 5000, 70_000, 1_000_001])
def test_capacity_growth_has_room_for_the_pairs_to_double(needed):
    """"one" (a program per capacity): a fitted capacity holds twice the pairs it was fitted to (one
    densification doubling, or a view needing twice as many) before it overflows; "per-size" keeps
    1.25x. Both round up to the power-of-two bucket and never shrink."""
    one, per = padding.TrainPadding("one", CAMS), padding.TrainPadding("per-size", CAMS)
    for pad, room in ((one, 2.0), (per, 1.25)):
        cap = pad.capacity(needed)
        assert cap.pairs >= room * needed and cap.pairs & (cap.pairs - 1) == 0
        assert cap == Capacity.fit(room * needed)
        assert pad.capacity(needed, minimum=Capacity(1 << 22)).pairs == max(1 << 22, cap.pairs)
    # An overflow at the fitted capacity (the need grew past it) grows it to hold twice the new need.
    cap = one.capacity(needed)
    grown = one.capacity(cap.pairs + 1, minimum=cap)
    assert grown.pairs >= 2 * (cap.pairs + 1)


def test_a_capacity_in_use_is_kept_until_the_pairs_near_it():
    """A refit keeps the capacity in use (no new program) while it holds 1.25x the pairs, then grows
    it by the policy's headroom; for "per-size" that is the fit itself (its headroom is 1.25x)."""
    one, per = padding.TrainPadding("one", CAMS), padding.TrainPadding("per-size", CAMS)
    cap = Capacity(1 << 16)
    assert one.capacity(0.8 * cap.pairs, current=cap) == cap  # (2x would be 2^17: kept)
    assert one.capacity(0.81 * cap.pairs, current=cap) == Capacity.fit(2 * 0.81 * cap.pairs)
    assert one.capacity(10, minimum=Capacity(1 << 18), current=cap) == Capacity(1 << 18)
    for needed in (100, 0.5 * cap.pairs, 0.8 * cap.pairs, 0.81 * cap.pairs, 3 * cap.pairs):
        assert per.capacity(needed, current=cap) == Capacity.fit(1.25 * needed, minimum=cap)
