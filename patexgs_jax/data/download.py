"""The paper's three datasets, fetched and laid out for the loaders.

    python -m patexgs_jax.data.download {mipnerf360,tandt_db,all} DEST [--mirror URL]
        [--sha256 NAME=HEX ...] [--keep-archives]

``mipnerf360`` fetches ``360_v2.zip`` (bicycle, garden, stump, room, counter, kitchen, bonsai) and
``360_extra_scenes.zip`` (flowers, treehill) from the Mip-NeRF 360 release, ``tandt_db`` the 3DGS
authors' ``tandt_db.zip`` (Tanks and Temples truck and train, Deep Blending drjohnson and playroom,
COLMAP scenes), ``all`` the three. They are extracted into ``DEST/360_v2/<scene>``,
``DEST/tandt/<scene>`` and ``DEST/db/<scene>``, the layout ``python -m experiments.mipnerf360 --data
DEST`` reads (:mod:`patexgs_jax.data.benchmarks`); the command ends by printing that command line.

How a download goes (pooch fetches each archive, :data:`ARCHIVES` names them):

* Bytes arrive in ``DEST/<name>.part``, with a progress bar (size, speed) when stderr is a
  terminal; an interrupted transfer (network failure, Ctrl-C, a truncated response) leaves the
  ``.part`` file and the same command resumes it (an HTTP ``Range`` request; a server that ignores
  it sends the whole file again).
* The file gets its name (``DEST/<name>``) only once every byte the server announced
  (``Content-Length``, or the total of its ``Content-Range``) has arrived, and, where a SHA-256 is
  pinned or given (``--sha256 NAME=HEX``), only if it matches: a partial or mismatching file is
  never taken for the archive (a mismatching one is deleted).
* The archive is then checked before anything is extracted (:func:`check_archive`): every member
  is read and its CRC-32 compared with the one the zip records, and the scene folders the layout
  needs must be there. A corrupt member or a missing scene refuses the archive, naming it; nothing
  is extracted and the file is deleted (the same command downloads it anew).
* The free disk space is checked first: the bytes still to fetch and, again, the archive's size for
  its extraction.
* Extraction goes into a temporary folder of DEST; each scene is then renamed into place and
  ``DEST/.patexgs_downloads/<name>.json`` records it, with the archive's SHA-256 computed here, its
  size and its source, so a second run finds every scene there and fetches nothing. The archive is
  deleted after extraction (``--keep-archives`` keeps it).
* ``--mirror URL`` takes each archive from ``URL/<its file name>`` (a lab's copy), checked the same
  way.

Checksums: no SHA-256 is pinned for the public archives (:data:`ARCHIVES`: ``None``); the server's
size, the zip's own CRC-32 of every member and the scene list check them instead, and the SHA-256
computed is recorded beside the data (compare it with a copy you trust). A SHA-256 given with
``--sha256 NAME=HEX`` is checked before the archive is used. Tests pass their own table of
``{name: (sha256, size)}`` to :func:`download` (``registry=``).
"""

from __future__ import annotations

import argparse
import dataclasses
import http.client
import json
import os
import shutil
import sys
import time
import urllib.error
import urllib.request
import zipfile
import zlib
from pathlib import Path

import pooch
from tqdm import tqdm

from .. import progress

__all__ = ["ARCHIVES", "SETS", "Archive", "DownloadError", "check_archive", "download", "main"]


class DownloadError(RuntimeError):
    """A dataset archive could not be fetched, checked or extracted; the message says which, from
    where, and what to do."""


@dataclasses.dataclass(frozen=True)
class Archive:
    """One public archive of the paper's datasets.

    Attributes:
      name: its file name (also its name under ``--mirror URL``).
      url: where it is published.
      folder: the folder of DEST its scenes go to (``""``: DEST itself).
      scenes: the scene folders it holds, relative to its top level (and to ``DEST/folder``).
      sha256: its pinned SHA-256 (hex), or None where this version pins none yet.
      size: its pinned size in bytes, or None where this version pins none yet.
    """

    name: str
    url: str
    folder: str
    scenes: tuple[str, ...]
    sha256: str | None = None
    size: int | None = None


#: The archives, by file name. No SHA-256 or byte size is pinned: none could be computed from the
#: published files where this code was written (no network), and none is published beside them.
#: An archive is taken when its transfer has the server's size, every member passes the zip's own
#: CRC-32 and its scenes are there; the SHA-256 computed is recorded (``--sha256`` checks a known
#: one). Public reports put 360_v2.zip at about 12.5 GB and tandt_db.zip at about 650 MB
#: (unverified; not used by the code).
ARCHIVES = {
    a.name: a for a in (
        Archive("360_v2.zip", "http://storage.googleapis.com/gresearch/refraw360/360_v2.zip", "360_v2",
                ("bicycle", "garden", "stump", "room", "counter", "kitchen", "bonsai")),
        Archive("360_extra_scenes.zip", "https://storage.googleapis.com/gresearch/refraw360/360_extra_scenes.zip",
                "360_v2", ("flowers", "treehill")),
        Archive("tandt_db.zip", "https://repo-sam.inria.fr/fungraph/3d-gaussian-splatting/datasets/input/tandt_db.zip",
                "", ("tandt/truck", "tandt/train", "db/drjohnson", "db/playroom")),
    )
}
#: The command's first argument: which archives it fetches.
SETS = {"mipnerf360": ("360_v2.zip", "360_extra_scenes.zip"), "tandt_db": ("tandt_db.zip",),
        "all": ("360_v2.zip", "360_extra_scenes.zip", "tandt_db.zip")}
#: Where the records of extracted archives are kept, under DEST.
RECORDS = ".patexgs_downloads"
_CHUNK = 1 << 20


def _free_bytes(folder: Path) -> int:
    return shutil.disk_usage(folder).free


def _gb(n: float) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e8 else f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{int(n)} bytes"


def _check_space(folder: Path, need: int, what: str) -> None:
    free = _free_bytes(folder)
    if need > free:
        raise DownloadError(f"{what} needs {_gb(need)} free on the disk of {folder}, which has {_gb(free)}: free "
                            "some space or choose another DEST, then run the same command again.")


def _network_hint(url: str) -> str:
    return (f"Check the network connection (and a proxy, HTTPS_PROXY) and run the same command again: it resumes "
            f"where it stopped. Or fetch {url} another way into a folder served over HTTP and pass its address "
            "with --mirror URL.")


class _ResumingDownload:
    """A pooch downloader (``downloader(url, output_file, pooch)``) that keeps the bytes in
    ``part`` across interrupted runs and asks for the rest with an HTTP ``Range`` request; only a
    transfer that delivered every announced byte is handed on (renamed to ``output_file``, pooch's
    temporary file, whose hash pooch checks before giving it the archive's name)."""

    def __init__(self, part: Path, size: int | None, show: bool, timeout: float = 60.0):
        self.part = part
        self.size = size
        self.show = show
        self.timeout = timeout
        self.total: int | None = None  # the bytes of the complete transfer, once it is complete

    def __call__(self, fname: str, action, pooch=None, *, check_only: bool | None = None) -> None:
        # pooch's downloader protocol: ``fname`` is the URL, ``action`` the temporary file to fill.
        url, output_file = fname, action
        offset = self.part.stat().st_size if self.part.is_file() else 0
        if self.size is not None and offset > self.size:  # not a prefix of the pinned file: start over
            self.part.unlink()
            offset = 0
        if offset and self.size is not None and offset == self.size:  # every byte there already
            os.replace(self.part, output_file)
            self.total = offset
            return
        headers = {"User-Agent": "patexgs_jax-download"}
        if offset:
            headers["Range"] = f"bytes={offset}-"
        try:
            resp = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=self.timeout)
        except urllib.error.HTTPError as e:
            if e.code == 416 and offset:  # the range starts at or past the end: start over
                self.part.unlink()
                return self(url, output_file, pooch)
            raise DownloadError(f"{url} answered HTTP {e.code} ({e.reason}): the server refused or failed the "
                                f"request. {_network_hint(url)}") from None
        except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
            reason = getattr(e, "reason", e)
            raise DownloadError(f"cannot download {url} ({reason}). {_network_hint(url)}") from None
        with resp:
            total = None
            if offset and resp.status == 206:
                rng = resp.headers.get("Content-Range", "")  # "bytes START-END/TOTAL"
                try:
                    start = int(rng.split()[1].split("-")[0])
                    total = int(rng.split("/")[1])
                except (IndexError, ValueError):
                    start = -1
                if start != offset:
                    raise DownloadError(f"{url} answered the request for the bytes from {offset} on with "
                                        f"{rng!r}; delete {self.part} and run the same command again.")
            else:
                offset = 0  # the whole file (the server ignored the range, or none was asked)
                length = resp.headers.get("Content-Length")
                total = int(length) if length and length.isdigit() else None
            if self.size is not None and total is not None and total != self.size:
                raise DownloadError(f"{url} serves {total} bytes where {Path(url).name} is pinned at {self.size}: "
                                    "it is not the archive this code knows (a changed release, or a wrong "
                                    "--mirror). Nothing was kept.")
            total = total if total is not None else self.size
            if total is not None:
                _check_space(self.part.parent, (total - offset) + total,
                             f"{Path(url).name} ({_gb(total)}, and as much again to extract it)")
            received = offset
            bar = tqdm(total=total, initial=offset, unit="B", unit_scale=True, unit_divisor=1024,
                       desc=Path(url).name, file=sys.stderr, disable=not self.show, dynamic_ncols=True)
            try:
                with open(self.part, "ab" if offset else "wb") as f:
                    while True:
                        chunk = resp.read(_CHUNK)
                        if not chunk:
                            break
                        f.write(chunk)
                        received += len(chunk)
                        bar.update(len(chunk))
            except (OSError, http.client.HTTPException) as e:
                raise DownloadError(f"the transfer of {url} stopped at {received} of {total or '?'} bytes ({e}); "
                                    f"{received} bytes are kept in {self.part}. {_network_hint(url)}") from None
            finally:
                bar.close()
        if total is not None and received != total:
            raise DownloadError(f"the transfer of {url} ended at {received} of {total} bytes (a truncated "
                                f"response); they are kept in {self.part}. {_network_hint(url)}")
        os.replace(self.part, output_file)
        self.total = received


def _record_path(dest: Path, archive: Archive) -> Path:
    return dest / RECORDS / f"{archive.name}.json"


def _scene_dirs(dest: Path, archive: Archive) -> list[Path]:
    return [dest / archive.folder / s for s in archive.scenes]


def _is_done(dest: Path, archive: Archive) -> bool:
    """Whether ``archive`` was extracted into ``dest`` (its record there, and every scene)."""
    return _record_path(dest, archive).is_file() and all(p.is_dir() for p in _scene_dirs(dest, archive))


def _archive_root(names, archive: Archive) -> str:
    """The folder of the zip (``""`` or ``"top/"``) that holds ``archive``'s scenes: an archive whose
    contents sit under one folder (e.g. ``tandt_db/``) is read from inside it."""
    tops = {s.split("/")[0] for s in archive.scenes}
    names = [n for n in names if n.strip("/") and not n.startswith(("__MACOSX", "."))]
    root = ""
    while True:
        inner = [n[len(root):] for n in names if n.startswith(root) and n != root]
        firsts = {n.split("/")[0] for n in inner}
        nested = all("/" in n for n in inner)  # (a file at this level: the contents start here)
        if len(firsts) == 1 and nested and next(iter(firsts)) not in tops:
            root += next(iter(firsts)) + "/"
        else:
            return root


def check_archive(path, archive: Archive, *, show: bool = False) -> dict:
    """Checks the zip ``path`` before anything of it is extracted: it opens as a zip, every scene
    folder of ``archive`` is in it, and every member reads back with the CRC-32 the zip records.

    Args:
      path: the downloaded archive.
      archive: what it should hold (:attr:`Archive.scenes`).
      show: draw a progress bar over the bytes read.
    Returns:
      ``{"root": the folder of the zip holding the scenes ("" or "top/"), "members": their number,
      "bytes": their uncompressed size}``.
    Raises:
      DownloadError: not a zip, a scene missing, or a member that does not read back (its name).
    """
    path = Path(path)
    name = None  # the member being read
    try:
        with zipfile.ZipFile(path) as z:
            members = [m for m in z.infolist() if not m.is_dir()]
            root = _archive_root(z.namelist(), archive)
            missing = [s for s in archive.scenes if not any(n.startswith(f"{root}{s}/") for n in z.namelist())]
            if missing:
                raise DownloadError(f"{archive.name} holds no {', '.join(missing)} (its scenes: "
                                    f"{', '.join(archive.scenes)}): it is not the archive this code knows (a changed "
                                    "release, or a wrong --mirror); nothing was extracted.")
            total = sum(m.file_size for m in members)
            bar = tqdm(total=total, unit="B", unit_scale=True, unit_divisor=1024, desc=f"checking {archive.name}",
                       file=sys.stderr, disable=not show, dynamic_ncols=True)
            try:
                for m in members:
                    name = m.filename
                    # zipfile compares the CRC-32 of what it read with the recorded one at the end.
                    with z.open(m) as f:
                        while f.read(_CHUNK):
                            pass
                    bar.update(m.file_size)
            finally:
                bar.close()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, EOFError, OSError, NotImplementedError) as e:
        what = f"it is not a readable zip ({e})" if name is None else f"its member {name!r} does not read back ({e})"
        raise DownloadError(f"{path}: {what}: the archive is corrupt; nothing was extracted.") from None
    return dict(root=root, members=len(members), bytes=total)


def _extract(path: Path, dest: Path, archive: Archive, record: dict, root: str) -> None:
    """Extracts ``path`` (checked by :func:`check_archive`; its scenes under ``root``) into a
    temporary folder of ``dest``, renames each scene into ``dest/folder`` (replacing a scene folder
    of that name) and writes the record (``record`` and the scenes)."""
    tmp = dest / f".extracting-{archive.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with zipfile.ZipFile(path) as z:
            _check_space(dest, sum(m.file_size for m in z.infolist()), f"extracting {archive.name}")
            z.extractall(tmp)
    except (zipfile.BadZipFile, OSError) as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise DownloadError(f"extracting {path} into {tmp} failed ({e}); nothing was moved into place: free some "
                            "space or fix the folder, then run the same command again.") from None
    base = tmp / root
    for s in archive.scenes:
        target = dest / archive.folder / s
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists():
            shutil.rmtree(target)
        os.replace(base / s, target)
    shutil.rmtree(tmp, ignore_errors=True)
    path_ = _record_path(dest, archive)
    path_.parent.mkdir(parents=True, exist_ok=True)
    path_.write_text(json.dumps(dict(archive=archive.name, **record,
                                     scenes=[str(p.relative_to(dest)) for p in _scene_dirs(dest, archive)],
                                     extracted=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())), indent=1))


def _fetch(archive: Archive, dest: Path, url: str, sha256: str | None, show: bool) -> tuple[Path, int | None]:
    """The archive's complete file in ``dest`` and the bytes the server announced for it (None
    when the file was there already), downloaded (resumed) unless it is there already, its
    SHA-256 checked when known (pooch)."""
    path = dest / archive.name
    if path.is_file():  # (a file gets its name only once its transfer is complete)
        if sha256 is not None and pooch.file_hash(str(path)) != sha256:
            raise DownloadError(f"{path} is there but its SHA-256 is not {sha256} (pinned, or given with "
                                "--sha256): if that value is right, delete the file and run the same command again "
                                "to download it anew.")
        return path, None
    if archive.size is not None:
        part = path.with_name(path.name + ".part")
        have = part.stat().st_size if part.is_file() else 0
        _check_space(dest, max(archive.size - have, 0) + archive.size,
                     f"{archive.name} ({_gb(archive.size)}, and as much again to extract it)")
    downloader = _ResumingDownload(path.with_name(path.name + ".part"), archive.size, show)
    try:
        pooch.retrieve(url, known_hash=None if sha256 is None else f"sha256:{sha256}", fname=archive.name,
                       path=dest, downloader=downloader)
    except ValueError as e:  # pooch: the hash of the complete transfer does not match
        raise DownloadError(f"{archive.name} from {url} does not match its SHA-256, pinned or given with --sha256 "
                            f"({e}); the file was deleted and nothing was extracted. Run the same command again "
                            "to download it anew; if it fails the same way the server holds another file than "
                            "that checksum's (a changed release, or a wrong --mirror or --sha256).") from None
    return path, downloader.total


def download(which: str, dest, *, mirror: str | None = None, registry: dict | None = None,
             sha256: dict | None = None, keep_archives: bool = False, show: bool | None = None,
             verbose: bool = True) -> list[Path]:
    """Fetches and extracts the archives of ``which`` into ``dest``; returns the scene folders.

    Args:
      which: ``"mipnerf360"``, ``"tandt_db"`` or ``"all"`` (:data:`SETS`).
      dest: the folder the datasets go to (made if missing).
      mirror: a base URL to take each archive from (``mirror/<name>``) instead of its own.
      registry: ``{name: (sha256, size)}`` replacing the pinned values of those archives (for tests,
        and for a lab's own pinned copies).
      sha256: ``{name: hex}`` SHA-256 values given by the user (``--sha256``), checked before the
        archive is used (replacing a pinned one).
      keep_archives: keep each archive after extraction (default: deleted).
      show: draw progress bars (default: :func:`patexgs_jax.progress.enabled`).
      verbose: print what is done.

    Raises:
      DownloadError: a network failure, a server error, a transfer shorter than the server announced
        (kept for resuming), a SHA-256 or pinned size that does not match, a corrupt member or a
        missing scene (:func:`check_archive`: nothing extracted, the file deleted), or too little
        disk space.
    """
    if which not in SETS:
        raise DownloadError(f"unknown dataset set {which!r}: use one of {', '.join(SETS)}.")
    dest = Path(dest)
    try:
        dest.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DownloadError(f"cannot make {dest} ({e}): choose a writable DEST.") from None
    show = progress.enabled() if show is None else show
    pooch.get_logger().setLevel("WARNING")  # its own lines say what ours do
    given = {k: v.lower() for k, v in (sha256 or {}).items()}
    unknown = [k for k in given if k not in ARCHIVES]
    if unknown:
        raise DownloadError(f"--sha256 names {', '.join(unknown)}, which is not one of {', '.join(ARCHIVES)}.")
    say = print if verbose else (lambda *a, **k: None)
    scenes: list[Path] = []
    for name in SETS[which]:
        archive = ARCHIVES[name]
        if registry and name in registry:
            pinned, size = registry[name]
            archive = dataclasses.replace(archive, sha256=pinned, size=size)
        if name in given:
            archive = dataclasses.replace(archive, sha256=given[name])
        url = archive.url if mirror is None else f"{mirror.rstrip('/')}/{name}"
        if _is_done(dest, archive):
            say(f"{name}: already extracted ({', '.join(archive.scenes)} in {dest / archive.folder}); nothing "
                "downloaded", flush=True)
            scenes += _scene_dirs(dest, archive)
            continue
        say(f"{name}: from {url}", flush=True)
        path, announced = _fetch(archive, dest, url, archive.sha256, show)
        say(f"{name}: checking its members' CRC-32 and scenes before extracting", flush=True)
        try:
            info = check_archive(path, archive, show=show)
        except DownloadError as e:
            path.unlink()
            raise DownloadError(f"{e} {path.name} was deleted: run the same command again to download it anew; "
                                "if it fails the same way, the server's copy is not the archive this code takes "
                                "(try another --mirror URL).") from None
        digest = archive.sha256 or pooch.file_hash(str(path))
        how = ("given (--sha256)" if name in given else "pinned") if archive.sha256 else "computed here, not compared"
        record = dict(source=url, sha256=digest, sha256_is=how, size=path.stat().st_size, server_size=announced,
                      members=info["members"], crc32="every member checked")
        _extract(path, dest, archive, record, info["root"])
        if not keep_archives:
            path.unlink()
        say(f"{name}: extracted {', '.join(archive.scenes)} into {dest / archive.folder} (SHA-256 {digest}, "
            f"recorded in {_record_path(dest, archive)})", flush=True)
        scenes += _scene_dirs(dest, archive)
    return scenes


def study_command(which: str, dest) -> str:
    """The ``experiments.mipnerf360`` command line that runs the paper's Tables 1 and 2 on what
    ``which`` downloaded into ``dest``."""
    data = Path(dest) / "360_v2" if which == "mipnerf360" else Path(dest)
    return f"python -m experiments.mipnerf360 --data {data} --methods tables --out runs/paper"


def _sha256_arg(text: str) -> tuple[str, str]:
    name, eq, hexd = text.partition("=")
    hexd = hexd.strip().lower()
    if not eq or len(hexd) != 64 or any(c not in "0123456789abcdef" for c in hexd):
        raise argparse.ArgumentTypeError(f"--sha256 takes NAME=HEX with a 64-digit SHA-256, got {text!r}")
    return name.strip(), hexd


def main(argv=None, *, registry: dict | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.data.download", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("which", choices=list(SETS), help="mipnerf360 (360_v2.zip, 360_extra_scenes.zip), tandt_db "
                    "(tandt_db.zip) or all")
    ap.add_argument("dest", help="the folder the datasets go to (360_v2/, tandt/, db/)")
    ap.add_argument("--mirror", default=None, help="take each archive from URL/<its file name>, with the same "
                    "checksums")
    ap.add_argument("--sha256", action="append", type=_sha256_arg, default=[], metavar="NAME=HEX",
                    help="a known SHA-256 of an archive, checked before it is extracted (none is needed: the "
                    "server's size and the zip's CRC-32s check it, and the SHA-256 computed is recorded)")
    ap.add_argument("--keep-archives", action="store_true", help="keep each archive after extracting it")
    args = ap.parse_args(argv)
    try:
        download(args.which, args.dest, mirror=args.mirror, registry=registry, sha256=dict(args.sha256),
                 keep_archives=args.keep_archives)
    except DownloadError as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        print("\nstopped: the bytes received are kept in DEST/<archive>.part; the same command resumes.",
              file=sys.stderr, flush=True)
        return 130
    print("\nThe paper's Tables 1 and 2 on these scenes (the Gaussian budget rows: add --budgets 100%,10%,1%):\n"
          f"  {study_command(args.which, args.dest)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
