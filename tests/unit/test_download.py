"""``python -m patexgs_jax.data.download`` against a local HTTP server (127.0.0.1, started here)
serving small archives made here, laid out as 3DGS distributes Tanks and Temples and Deep Blending
(and as the Mip-NeRF 360 release): the happy path without a pinned checksum (the scenes load under
their datasets' protocols, the SHA-256 computed is recorded), an interrupted transfer that resumes,
a truncated response, a corrupt member and a missing scene (refused, nothing extracted), a wrong
--sha256 or pinned checksum, a size other than the pinned one, a server error, too little disk
space, and a second run that downloads nothing. No test reaches the internet."""

from __future__ import annotations

import hashlib
import http.server
import io
import json
import threading
import zipfile
from pathlib import Path

import pytest

from patexgs_jax.data import download as dl


class _Server:
    """A bounded local HTTP server of ``files`` (name -> bytes) that honours ``Range: bytes=N-`` and
    can misbehave per file: ``cut[name] = n`` announces the whole file but sends its first n bytes
    and closes; ``fail[name] = code`` answers that HTTP error. ``requests`` lists (name, Range)."""

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.cut: dict[str, int] = {}
        self.fail: dict[str, int] = {}
        self.requests: list[tuple[str, str | None]] = []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            timeout = 10  # a stuck client cannot hold the test

            def do_GET(self):
                name = self.path.lstrip("/")
                rng = self.headers.get("Range")
                server.requests.append((name, rng))
                if name in server.fail:
                    self.send_error(server.fail[name])
                    return
                data = server.files.get(name)
                if data is None:
                    self.send_error(404)
                    return
                start = int(rng.split("=")[1].split("-")[0]) if rng else 0
                if start >= len(data) and rng:
                    self.send_response(416)
                    self.send_header("Content-Range", f"bytes */{len(data)}")
                    self.end_headers()
                    return
                body = data[start:]
                self.send_response(206 if rng else 200)
                if rng:
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                cut = server.cut.pop(name, None)
                self.wfile.write(body if cut is None else body[:cut])
                self.wfile.flush()
                if cut is not None:
                    self.close_connection = True

            def log_message(self, *args):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs=dict(poll_interval=0.05), daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)


@pytest.fixture
def server():
    with _Server() as s:
        yield s


def _zip(tree: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in tree.items():
            z.writestr(name, data)
    return buf.getvalue()


def _zip_folder(root: Path) -> bytes:
    return _zip({str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()})


def _pin(data: bytes) -> tuple[str, int]:
    return hashlib.sha256(data).hexdigest(), len(data)


def _small_archive(name: str = "tandt_db.zip", drop: str | None = None, top: str = "") -> bytes:
    """An archive of tiny files in ``name``'s layout (enough to extract), without the scene ``drop``,
    its contents under the folder ``top`` (e.g. ``"tandt_db/"``)."""
    return _zip({f"{top}{s}/{part}": b"x" * 3000 for s in dl.ARCHIVES[name].scenes if s != drop
                 for part in ("images/a.jpg", "sparse/0/cameras.bin")})


def _small_tandt_db() -> bytes:
    return _small_archive()


def _corrupt(data: bytes, member: str) -> bytes:
    """``data`` (a zip of stored members) with one byte of ``member``'s contents changed: its
    CRC-32 no longer matches."""
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        info = z.getinfo(member)
    fixed = 30 + len(info.filename.encode()) + len(info.extra)  # the local header before the bytes
    at = info.header_offset + fixed + 100
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:]


def _nothing_extracted(dest: Path) -> bool:
    return not any(p.name in ("tandt", "db", "360_v2", ".patexgs_downloads") or p.name.startswith(".extracting")
                   for p in dest.iterdir())


@pytest.fixture(scope="module")
def scene_archive(tmp_path_factory):
    """tandt_db.zip made from a tiny synthetic scene laid out as 3DGS distributes it (tandt/truck,
    tandt/train, db/drjohnson, db/playroom), and its bytes."""
    from data_builders import make_3dgs_layout
    from patexgs_jax.data.synthetic import generate

    base = tmp_path_factory.mktemp("archive")
    scene = generate(base / "synthetic", seed=0, num_views=9, width=32, height=24, supersample=1, num_points=100,
                     verbose=False)
    make_3dgs_layout(scene, base / "tree", {"tandt": ["truck", "train"], "db": ["drjohnson", "playroom"]})
    return _zip_folder(base / "tree")


def test_download_extracts_loads_and_a_second_run_fetches_nothing(server, scene_archive, tmp_path, capsys):
    """The happy path end to end through the command line, as the public archives are (no SHA-256
    pinned, none given): the archive from ``--mirror``, checked (size, CRC-32s, scenes), extracted
    into tandt/ and db/ with its computed SHA-256 recorded, each scene loading under its dataset's
    protocol (the images' own size, every 8th image held out); the command printed runs on it; a
    second run downloads nothing."""
    from experiments import mipnerf360 as mn
    from patexgs_jax.data import load

    server.files["tandt_db.zip"] = scene_archive
    registry = None  # the shipped table: nothing pinned
    dest = tmp_path / "data"
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url], registry=registry) == 0
    out = capsys.readouterr().out
    assert f"python -m experiments.mipnerf360 --data {dest} --methods tables" in out
    digest, size = _pin(scene_archive)
    record = json.loads((dest / ".patexgs_downloads" / "tandt_db.zip.json").read_text())
    assert record["sha256"] == digest and record["size"] == record["server_size"] == size
    assert record["sha256_is"] == "computed here, not compared" and f"SHA-256 {digest}" in out
    assert not any(p.name.startswith(".extracting") for p in dest.iterdir())
    assert server.requests == [("tandt_db.zip", None)]
    assert not (dest / "tandt_db.zip").exists() and not list(dest.glob("*.part"))  # deleted after extraction
    scenes = mn.find_scenes(dest)
    assert list(scenes) == ["truck", "train", "drjohnson", "playroom"]  # the paper's order
    protocols = mn.scene_protocols(scenes)
    assert {n: p.dataset for n, p in protocols.items()} == {"truck": "tandt", "train": "tandt", "drjohnson": "db",
                                                              "playroom": "db"}
    assert all(p.factor == 1 and p.test_every == 8 for p in protocols.values())
    assert "its parent folder is tandt/" in protocols["train"].why and "own size" in protocols["train"].why
    ds = load(scenes["drjohnson"], factor=protocols["drjohnson"].factor, verbose=False)
    assert ds.factor == 1 and ds.train_views[0].camera.width == 32 and [v.name for v in ds.test_views] == [
        "img_0000.png", "img_0008.png"]
    record = protocols["drjohnson"].record(ds)
    assert record["training_size"] == [32, 24] and record["test_views"] == 2 and record["dataset"] == "db"
    # Second run: everything is there, nothing is requested.
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url], registry=registry) == 0
    assert len(server.requests) == 1
    assert "already extracted" in capsys.readouterr().out


def test_an_interrupted_transfer_resumes_and_a_truncated_one_is_never_complete(server, tmp_path):
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    server.cut["tandt_db.zip"] = 5000  # the connection drops after 5000 bytes of the announced ones
    registry = {"tandt_db.zip": _pin(data)}
    dest = tmp_path / "d"
    with pytest.raises(dl.DownloadError, match=r"ended at 5000 of \d+ bytes.*run the same command again"):
        dl.download("tandt_db", dest, mirror=server.url, registry=registry, verbose=False)
    assert (dest / "tandt_db.zip.part").stat().st_size == 5000
    assert not (dest / "tandt_db.zip").exists() and not (dest / "tandt").exists()  # never taken as complete
    got = dl.download("tandt_db", dest, mirror=server.url, registry=registry, verbose=False)
    assert server.requests[-1] == ("tandt_db.zip", "bytes=5000-")  # only the rest was asked for
    assert [p.relative_to(dest).as_posix() for p in got] == list(dl.ARCHIVES["tandt_db.zip"].scenes)
    assert (dest / "db" / "playroom" / "images" / "a.jpg").read_bytes() == b"x" * 3000
    assert not (dest / "tandt_db.zip.part").exists()


def test_a_wrong_checksum_deletes_the_file_and_extracts_nothing(server, tmp_path):
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    dest = tmp_path / "d"
    wrong = {"tandt_db.zip": ("0" * 64, len(data))}
    with pytest.raises(dl.DownloadError, match=r"does not match its SHA-256, pinned.*nothing was extracted"):
        dl.download("tandt_db", dest, mirror=server.url, registry=wrong, verbose=False)
    assert sorted(p.name for p in dest.iterdir()) == []
    # A server whose file has another size than the pinned one: refused before a byte is kept.
    with pytest.raises(dl.DownloadError, match=r"serves \d+ bytes where tandt_db.zip is pinned at 7"):
        dl.download("tandt_db", dest, mirror=server.url, registry={"tandt_db.zip": ("0" * 64, 7)}, verbose=False)


def test_server_and_network_errors_name_the_url_and_the_fix(server, tmp_path):
    server.fail["tandt_db.zip"] = 503
    with pytest.raises(dl.DownloadError, match=rf"{server.url}/tandt_db.zip answered HTTP 503.*--mirror"):
        dl.download("tandt_db", tmp_path / "d", mirror=server.url, registry={"tandt_db.zip": ("0" * 64, 10)},
                    verbose=False)
    with pytest.raises(dl.DownloadError, match=r"cannot download http://127.0.0.1:9/tandt_db.zip.*run the same"):
        dl.download("tandt_db", tmp_path / "d", mirror="http://127.0.0.1:9", registry={"tandt_db.zip": ("0" * 64, 10)},
                    verbose=False)
    assert dl.main(["tandt_db", str(tmp_path / "d"), "--mirror", "http://127.0.0.1:9"]) == 2


def test_a_corrupt_member_refuses_the_archive_with_nothing_extracted(server, tmp_path, capsys):
    """Every member is read back against its CRC-32 before anything is extracted: one changed byte
    in the last scene's file refuses the archive (naming the member), extracts nothing and deletes
    the file; a good copy then extracts."""
    good = _small_tandt_db()
    server.files["tandt_db.zip"] = _corrupt(good, "db/playroom/images/a.jpg")
    dest = tmp_path / "d"
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url]) == 2
    err = capsys.readouterr().err
    assert "'db/playroom/images/a.jpg' does not read back" in err and "Bad CRC-32" in err, err
    assert "nothing was extracted" in err and "run the same command again" in err
    assert _nothing_extracted(dest) and not (dest / "tandt_db.zip").exists()
    server.files["tandt_db.zip"] = good
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url]) == 0
    assert (dest / "db" / "playroom" / "images" / "a.jpg").read_bytes() == b"x" * 3000


def test_a_missing_scene_refuses_the_archive(server, tmp_path):
    server.files["tandt_db.zip"] = _small_archive(drop="db/playroom", top="tandt_db/")
    dest = tmp_path / "d"
    with pytest.raises(dl.DownloadError, match=r"tandt_db.zip holds no db/playroom.*nothing was extracted"):
        dl.download("tandt_db", dest, mirror=server.url, verbose=False)
    assert _nothing_extracted(dest) and not (dest / "tandt_db.zip").exists()
    # The Mip-NeRF 360 archive needs its seven scenes (stump missing here).
    server.files["360_v2.zip"] = _small_archive("360_v2.zip", drop="stump")
    with pytest.raises(dl.DownloadError, match=r"360_v2.zip holds no stump"):
        dl.download("mipnerf360", dest, mirror=server.url, verbose=False)
    assert _nothing_extracted(dest)


def test_mipnerf360_archives_extract_also_from_under_a_top_folder(server, tmp_path):
    server.files["360_v2.zip"] = _small_archive("360_v2.zip")
    server.files["360_extra_scenes.zip"] = _small_archive("360_extra_scenes.zip", top="360_extra_scenes/")
    got = dl.download("mipnerf360", tmp_path / "d", mirror=server.url, verbose=False)
    assert sorted(p.name for p in got) == sorted(("bicycle", "bonsai", "counter", "garden", "kitchen", "room", "stump",
                                                  "flowers", "treehill"))
    assert all(p.parent == tmp_path / "d" / "360_v2" and (p / "sparse" / "0").is_dir() for p in got)


def test_a_given_sha256_is_checked(server, tmp_path, capsys):
    """``--sha256 NAME=HEX``: a wrong one refuses the archive (a fresh transfer is deleted; a file
    already there is kept, the value may be the wrong one); the right one extracts and is recorded
    as given."""
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    digest, _ = _pin(data)
    dest = tmp_path / "d"
    wrong = ["--sha256", f"tandt_db.zip={'1' * 64}"]
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url, *wrong]) == 2
    assert "does not match its SHA-256, pinned or given" in capsys.readouterr().err
    assert _nothing_extracted(dest) and not (dest / "tandt_db.zip").exists()
    (dest / "tandt_db.zip").write_bytes(data)  # (a copy already there)
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url, *wrong]) == 2
    assert "delete the file" in capsys.readouterr().err and (dest / "tandt_db.zip").is_file()
    assert _nothing_extracted(dest)
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url, "--sha256", f"tandt_db.zip={digest}"]) == 0
    assert len(server.requests) == 1 and (dest / "tandt" / "truck").is_dir()
    record = json.loads((dest / ".patexgs_downloads" / "tandt_db.zip.json").read_text())
    assert record["sha256"] == digest and record["sha256_is"] == "given (--sha256)"
    assert all(a.sha256 is None for a in dl.ARCHIVES.values())  # the shipped table pins none: see the module


def test_a_transfer_shorter_than_the_server_announced_is_refused(server, tmp_path):
    """Without a pinned size the server's Content-Length decides: a response cut short is kept for
    resuming, never checked or extracted."""
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    server.cut["tandt_db.zip"] = len(data) - 10
    dest = tmp_path / "d"
    with pytest.raises(dl.DownloadError, match=rf"ended at {len(data) - 10} of {len(data)} bytes"):
        dl.download("tandt_db", dest, mirror=server.url, verbose=False)
    assert _nothing_extracted(dest) and not (dest / "tandt_db.zip").exists()
    assert (dest / "tandt_db.zip.part").stat().st_size == len(data) - 10


def test_too_little_disk_space_stops_before_writing(server, tmp_path, monkeypatch):
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    monkeypatch.setattr(dl, "_free_bytes", lambda folder: 100)
    with pytest.raises(dl.DownloadError, match=r"needs .* free on the disk .* which has 100 bytes"):
        dl.download("tandt_db", tmp_path / "d", mirror=server.url, registry={"tandt_db.zip": _pin(data)},
                    verbose=False)
    assert not list((tmp_path / "d").iterdir())
    assert server.requests == []  # the pinned size decided it before any request
