"""The paper's three datasets, as 3DGS distributes them, and the protocol each scene is trained under.

* Mip-NeRF 360 (``360_v2/``: bicycle, flowers, garden, stump, treehill, room, counter, kitchen,
  bonsai): images downsampled by 4 outdoors and 2 indoors (:data:`.colmap.MIPNERF360_FACTORS`).
* Tanks and Temples (``tandt/``: truck, train) and Deep Blending (``db/``: drjohnson, playroom):
  COLMAP scenes (``images/`` and ``sparse/0``) trained at the images' own size (factor 1, no
  width limit).

Every dataset holds out every 8th name-sorted image for testing (3DGS's and the paper's protocol).
A scene's dataset is recognised from its parent folder (``360_v2``, ``tandt``, ``db``: the archives'
layout) and else from its name (the paper's scene names; ``train`` alone only under ``tandt/``, the
name being too common); :func:`protocol` says which applies and why, and a dataset can be named
instead of recognised.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from .colmap import MIPNERF360_FACTORS
from .errors import DatasetError

__all__ = [
    "DATASETS",
    "DATASET_FOLDERS",
    "DATASET_NAMES",
    "SCENES",
    "TEST_EVERY",
    "Protocol",
    "dataset_of",
    "protocol",
]

#: The paper's datasets, in the order of its Table 1's column groups.
DATASETS = ("mipnerf360", "tandt", "db")
#: Their names as the paper's tables print them.
DATASET_NAMES = {"mipnerf360": "Mip-NeRF 360", "tandt": "Tanks and Temples", "db": "Deep Blending"}
#: The folder each dataset's scenes sit in once its archive is extracted.
DATASET_FOLDERS = {"mipnerf360": "360_v2", "tandt": "tandt", "db": "db"}
#: The paper's scenes of each dataset (the order of its per-scene tables).
SCENES = {
    "mipnerf360": ("bicycle", "flowers", "garden", "stump", "treehill", "room", "counter", "kitchen", "bonsai"),
    "tandt": ("truck", "train"),
    "db": ("drjohnson", "playroom"),
}
#: Every dataset holds out every 8th name-sorted image (3DGS's protocol, the paper's).
TEST_EVERY = 8
# Names recognised without their parent folder: "train" is too common a folder name to mean Tanks
# and Temples by itself.
_BY_NAME = {**{s: "mipnerf360" for s in SCENES["mipnerf360"]}, "truck": "tandt",
            "drjohnson": "db", "playroom": "db"}


@dataclasses.dataclass(frozen=True)
class Protocol:
    """How one scene is trained and tested.

    Attributes:
      dataset: ``"mipnerf360"``, ``"tandt"``, ``"db"``, or None (a scene of none of them).
      factor: the image downsampling factor to load with; None: the loaders' default rule (images
        wider than 1600 px resized to 1600 wide, :func:`.colmap.default_resolution`).
      test_every: every ``test_every``-th name-sorted image is a test view.
      why: one sentence: what decided the dataset and the resolution.
    """

    dataset: str | None
    factor: int | None
    test_every: int
    why: str

    def record(self, dataset=None) -> dict:
        """The JSON record of the protocol (``results.json``'s ``scenes``), with the loaded
        :class:`~.dataset.Dataset`'s training size and test views when given."""
        out: dict = dict(dataset=self.dataset, factor=self.factor, test_every=self.test_every, why=self.why)
        if dataset is not None:
            cam = dataset.train_views[0].camera if dataset.train_views else dataset.views[0].camera
            out.update(training_size=[int(cam.width), int(cam.height)], applied_factor=float(dataset.factor),
                       train_views=len(dataset.train_views), test_views=len(dataset.test_views))
        return out


def dataset_of(path) -> tuple[str | None, str]:
    """``(dataset, reason)`` of a scene folder: from its parent folder (``360_v2``, ``tandt``,
    ``db``), else from its name (the paper's scene names, ``train`` only under ``tandt/``); None
    when neither names one of the paper's datasets."""
    p = Path(path).resolve()
    by_folder = {folder: d for d, folder in DATASET_FOLDERS.items()}
    if p.parent.name in by_folder:
        return by_folder[p.parent.name], f"its parent folder is {p.parent.name}/"
    if p.name in _BY_NAME:
        return _BY_NAME[p.name], f"{p.name} is a {DATASET_NAMES[_BY_NAME[p.name]]} scene name"
    return None, (f"neither its name ({p.name}) nor its parent folder ({p.parent.name}/) names one of the "
                  "paper's datasets")


def protocol(path, dataset: str | None = None, factor: int | None = None) -> Protocol:
    """The protocol of the scene at ``path``.

    Args:
      path: the scene folder.
      dataset: ``"mipnerf360"``, ``"tandt"`` or ``"db"`` to name the dataset (``--dataset``) instead
        of recognising it (:func:`dataset_of`).
      factor: an explicit downsampling factor (``--factor``), which every dataset then uses.

    Raises:
      DatasetError: an unknown ``dataset``, or ``"mipnerf360"`` named for a scene that is not one
        of its nine without a ``factor`` (its factors are per scene).
    """
    name = Path(path).resolve().name
    if dataset is not None:
        if dataset not in DATASETS:
            raise DatasetError(f"unknown dataset {dataset!r}: use one of {', '.join(DATASETS)}.")
        reason = f"--dataset {dataset}"
    else:
        dataset, reason = dataset_of(path)
    held = f"every {TEST_EVERY}th image held out"
    if factor is not None:
        what = DATASET_NAMES.get(dataset or "", "not one of the paper's datasets")
        return Protocol(dataset, int(factor), TEST_EVERY,
                        f"{what} ({reason}): factor {factor} as given (--factor), {held}")
    if dataset == "mipnerf360":
        f = MIPNERF360_FACTORS.get(name)
        if f is None:
            raise DatasetError(f"scene {name} is not one of Mip-NeRF 360's nine ({', '.join(SCENES['mipnerf360'])}), "
                               "whose factors are per scene (4 outdoors, 2 indoors): pass --factor.")
        where = "outdoor" if f == 4 else "indoor"
        return Protocol(dataset, f, TEST_EVERY, f"Mip-NeRF 360 ({reason}): factor {f} (an {where} scene, the "
                        f"Mip-NeRF 360 protocol), {held}")
    if dataset in ("tandt", "db"):
        return Protocol(dataset, 1, TEST_EVERY, f"{DATASET_NAMES[dataset]} ({reason}): the images' own size "
                        f"(factor 1, no Mip-NeRF 360 factor, as 3DGS and the paper), {held}")
    return Protocol(None, None, TEST_EVERY, f"not one of the paper's datasets ({reason}): images wider than 1600 "
                    f"px resized to 1600 wide (the 3DGS rule), {held}")
