"""``python -m patexgs_jax.data.download`` against a local HTTP server (127.0.0.1, started here)
serving small archives made here, laid out as 3DGS distributes Tanks and Temples and Deep Blending:
the happy path (the scenes load under their datasets' protocols), an interrupted transfer that
resumes, a truncated response, a wrong checksum, a server error, an unpinned checksum, too little
disk space, and a second run that downloads nothing. No test reaches the internet."""

from __future__ import annotations

import hashlib
import http.server
import io
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


def _small_tandt_db() -> bytes:
    """A tandt_db.zip of tiny files in the archive's layout (enough to extract)."""
    return _zip({f"{s}/{part}": b"x" * 3000 for s in dl.ARCHIVES["tandt_db.zip"].scenes
                 for part in ("images/a.jpg", "sparse/0/cameras.bin")})


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
    """The happy path end to end through the command line: the archive from ``--mirror``, checked,
    extracted into tandt/ and db/, each scene loading under its dataset's protocol (the images' own
    size, every 8th image held out); the command printed runs on it; a second run downloads nothing."""
    from experiments import mipnerf360 as mn
    from patexgs_jax.data import load

    server.files["tandt_db.zip"] = scene_archive
    registry = {"tandt_db.zip": _pin(scene_archive)}
    dest = tmp_path / "data"
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url], registry=registry) == 0
    out = capsys.readouterr().out
    assert f"python -m experiments.mipnerf360 --data {dest} --methods tables" in out
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
    with pytest.raises(dl.DownloadError, match=r"does not match its pinned checksum.*nothing was extracted"):
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


def test_an_unpinned_archive_is_not_extracted_until_its_checksum_is_given(server, tmp_path, capsys):
    """Where no SHA-256 is pinned the archive is fetched, its SHA-256 printed and extraction refused;
    ``--sha256 NAME=HEX`` then extracts it without downloading it again (a wrong one is refused)."""
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    digest, _ = _pin(data)
    dest = tmp_path / "d"
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url], registry={"tandt_db.zip": (None, None)}) == 2
    err = capsys.readouterr().err
    assert f"--sha256 tandt_db.zip={digest}" in err and not (dest / "tandt").exists()
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url, "--sha256", f"tandt_db.zip={'1' * 64}"],
                   registry={"tandt_db.zip": (None, None)}) == 2
    assert "delete it" in capsys.readouterr().err
    assert dl.main(["tandt_db", str(dest), "--mirror", server.url, "--sha256", f"tandt_db.zip={digest}"],
                   registry={"tandt_db.zip": (None, None)}) == 0
    assert len(server.requests) == 1 and (dest / "tandt" / "truck").is_dir()
    assert all(a.sha256 is None for a in dl.ARCHIVES.values())  # this version pins none: see the module


def test_too_little_disk_space_stops_before_writing(server, tmp_path, monkeypatch):
    data = _small_tandt_db()
    server.files["tandt_db.zip"] = data
    monkeypatch.setattr(dl, "_free_bytes", lambda folder: 100)
    with pytest.raises(dl.DownloadError, match=r"needs .* free on the disk .* which has 100 bytes"):
        dl.download("tandt_db", tmp_path / "d", mirror=server.url, registry={"tandt_db.zip": _pin(data)},
                    verbose=False)
    assert not list((tmp_path / "d").iterdir())
    assert server.requests == []  # the pinned size decided it before any request
