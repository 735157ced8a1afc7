"""``python -m rgs_warp.download``: small archives served from a local HTTP server (a thread of the test)
in the datasets' own layouts: unpacked where the loaders read them, refused when tampered with (and
nothing left), resumed with a Range request after an interruption."""

import dataclasses
import hashlib
import io
import json
import shutil
import tarfile
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from rgs_warp.app.download import DownloadError, download, main
from rgs_warp.app.download_catalogue import CATALOGUE
from rgs_warp.config import group_options, load_config
from rgs_warp.datasets import DatasetError, open_dataset


class Server:
    """Files served over HTTP on 127.0.0.1 with Range requests; ``requests`` logs (path, Range header);
    ``cut_after`` sends the first response of a path only that far (the connection drops)."""

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.requests: list[tuple[str, str | None]] = []
        self.cut_after: dict[str, int] = {}
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                path = self.path.lstrip("/")
                server.requests.append((path, self.headers.get("Range")))
                data = server.files.get(path)
                if data is None:
                    self.send_error(404)
                    return
                start = 0
                if self.headers.get("Range"):
                    start = int(self.headers["Range"].removeprefix("bytes=").split("-")[0])
                    if start >= len(data):
                        self.send_error(416)
                        return
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                else:
                    self.send_response(200)
                self.send_header("Content-Length", str(len(data) - start))
                self.end_headers()
                body = data[start:]
                if path in server.cut_after:
                    body = body[: server.cut_after.pop(path)]
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, args=(0.05,), daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server():
    s = Server()
    yield s
    s.close()


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def tum_archive(folder: str, n: int = 2) -> bytes:
    """A .tgz of a TUM sequence folder: n frames of 640x480 (TUM's size; plain images compress to little)."""
    files = {
        "rgb.txt": "# colour\n" + "".join(f"{1.0 + k / 30:.6f} rgb/{k}.png\n" for k in range(n)),
        "depth.txt": "".join(f"{1.0 + k / 30 + 0.001:.6f} depth/{k}.png\n" for k in range(n)),
        "groundtruth.txt": "".join(f"{1.0 + k / 30:.6f} {0.01 * k} 0 0 0 0 0 1\n" for k in range(n)),
    }
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:

        def add(name: str, data: bytes):
            info = tarfile.TarInfo(f"{folder}/{name}")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))

        for name, text in files.items():
            add(name, text.encode())
        for k in range(n):
            add(f"rgb/{k}.png", png(np.full((480, 640, 3), 40 * k, np.uint8)))
            add(f"depth/{k}.png", png(np.full((480, 640), 5000, np.uint16)))
    return buffer.getvalue()


def unrecorded(name: str) -> dict:
    """The catalogue with ``name``'s archive stripped of its recorded size and SHA-256 (the test's own
    archive stands in for it)."""
    d = CATALOGUE[name]
    return {name: dataclasses.replace(d, archive=dataclasses.replace(d.archive, size=None, sha256=None))}


def left_in(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_catalogue_paths_are_the_dataset_configs_paths():
    """Each name that has a config (dataset=NAME) unpacks to that config's dataset.path."""
    named = [name for name in group_options("dataset") if name in CATALOGUE]
    assert {"tum/fr1_desk", "tum/fr3_office", "replica/office0", "7scenes/redkitchen"} <= set(named)
    for name in named:
        assert load_config([f"dataset={name}"]).dataset.path == CATALOGUE[name].path, name
    desk = CATALOGUE["tum/fr1_desk"].archive
    assert (desk.size, desk.sha256[:12]) == (344_011_403, "e983d6830916")
    assert desk.url() == "https://cvg.cit.tum.de/rgbd/dataset/freiburg1/rgbd_dataset_freiburg1_desk.tgz"


def test_download_unpacks_where_the_loader_reads_and_a_second_call_does_nothing(tmp_path, server):
    data = tum_archive("rgbd_dataset_freiburg1_desk")
    server.files["freiburg1/rgbd_dataset_freiburg1_desk.tgz"] = data
    catalogue = unrecorded("tum/fr1_desk")
    folders = download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=catalogue)
    assert folders == [tmp_path / "TUM" / "rgbd_dataset_freiburg1_desk"]
    ds = open_dataset(load_config(["dataset=tum/fr1_desk", f"data_root={tmp_path}"]))
    assert len(ds) == 2 and ds[1].rgb.shape == (480, 640, 3)
    # no archive, part or staging folder left; the SHA-256 recorded for the next download of it
    assert not list(tmp_path.rglob("*.part")) and not list(tmp_path.rglob(".unpacking-*"))
    records = json.loads((tmp_path / ".downloads" / "sha256.json").read_text())
    assert records["rgbd_dataset_freiburg1_desk.tgz"]["sha256"] == hashlib.sha256(data).hexdigest()
    server.requests.clear()
    download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=catalogue)
    assert server.requests == []  # present: nothing fetched
    # that record checks the next download: another file under the same name is refused
    shutil.rmtree(tmp_path / "TUM" / "rgbd_dataset_freiburg1_desk")
    server.files["freiburg1/rgbd_dataset_freiburg1_desk.tgz"] = tum_archive("rgbd_dataset_freiburg1_desk", n=3)
    with pytest.raises(DownloadError, match="recorded at its first download"):
        download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=catalogue)


def test_a_tampered_archive_is_refused_and_nothing_is_left(tmp_path, server, capsys):
    """fr1/desk's size and SHA-256 are on record: another file served for it is refused and removed, and
    nothing is unpacked; an archive without a record that cannot be unpacked likewise."""
    server.files["freiburg1/rgbd_dataset_freiburg1_desk.tgz"] = tum_archive("rgbd_dataset_freiburg1_desk")
    argv = ["tum/fr1_desk", "--data-root", str(tmp_path), "--base-url", server.url]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "344,011,403 expected" in err and "refused and removed" in err
    assert left_in(tmp_path) == []
    # a record-less archive cut short: gzip finds it truncated
    data = tum_archive("rgbd_dataset_freiburg1_desk")
    server.files["freiburg1/rgbd_dataset_freiburg1_desk.tgz"] = data[: len(data) // 2]
    with pytest.raises(DownloadError, match="cannot be unpacked .*nothing was unpacked"):
        download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=unrecorded("tum/fr1_desk"))
    assert left_in(tmp_path) == []
    # a known size and a SHA-256 that does not match
    catalogue = unrecorded("tum/fr1_desk")
    archive = dataclasses.replace(catalogue["tum/fr1_desk"].archive, size=len(data), sha256="0" * 64)
    catalogue["tum/fr1_desk"] = dataclasses.replace(catalogue["tum/fr1_desk"], archive=archive)
    server.files["freiburg1/rgbd_dataset_freiburg1_desk.tgz"] = data
    with pytest.raises(DownloadError, match=f"SHA-256 {hashlib.sha256(data).hexdigest()}, 0{{64}} expected"):
        download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=catalogue)
    assert left_in(tmp_path) == []


def test_an_interrupted_download_resumes_with_a_range_request(tmp_path, server):
    data = tum_archive("rgbd_dataset_freiburg1_desk", n=3)
    path = "freiburg1/rgbd_dataset_freiburg1_desk.tgz"
    server.files[path] = data
    server.cut_after[path] = 300  # the connection drops after 300 of its ~660 bytes
    catalogue = unrecorded("tum/fr1_desk")
    archive = dataclasses.replace(
        catalogue["tum/fr1_desk"].archive, size=len(data), sha256=hashlib.sha256(data).hexdigest()
    )
    catalogue["tum/fr1_desk"] = dataclasses.replace(catalogue["tum/fr1_desk"], archive=archive)
    with pytest.raises(DownloadError, match="interrupted after 300 bytes.*run the command again to resume"):
        download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=catalogue)
    assert (tmp_path / ".downloads" / "rgbd_dataset_freiburg1_desk.tgz.part").stat().st_size == 300
    download(["tum/fr1_desk"], tmp_path, server.url, progress=False, catalogue=catalogue)
    assert server.requests == [(path, None), (path, "bytes=300-")]
    assert len(open_dataset(load_config(["dataset=tum/fr1_desk", f"data_root={tmp_path}"]))) == 3


def test_replica_and_7scenes_unpack_in_the_loaders_layouts(tmp_path, server):
    """Replica: one zip for every scene, unpacked whole, and a scene missing later moved into the Replica
    folder that is there.  7-Scenes: a zip per scene holding a zip per sequence, unpacked in place."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("Replica/cam_params.json", json.dumps({"camera": dict(w=32, h=24, fx=30, fy=30, cx=15.5, cy=11.5)}))
        for scene in ("office0", "room0"):
            jpg = cv2.imencode(".jpg", np.full((24, 32, 3), 90, np.uint8))[1].tobytes()
            z.writestr(f"Replica/{scene}/results/frame000000.jpg", jpg)
            z.writestr(f"Replica/{scene}/results/depth000000.png", png(np.full((24, 32), 6553, np.uint16)))
            z.writestr(f"Replica/{scene}/traj.txt", " ".join(map(str, np.eye(4).ravel())) + "\n")
    server.files["Replica.zip"] = buffer.getvalue()
    download(["replica/office0"], tmp_path, server.url, progress=False, catalogue=CATALOGUE)
    for scene in ("office0", "room0"):
        ds = open_dataset(load_config([f"dataset=replica/{scene}", f"data_root={tmp_path}"]))
        assert len(ds) == 1 and ds[0].depth[0, 0] == pytest.approx(1.0, abs=1e-3)
    office = (tmp_path / "Replica" / "office0" / "traj.txt").stat()
    shutil.rmtree(tmp_path / "Replica" / "room0")
    download(["replica/room0", "replica/office0"], tmp_path, server.url, progress=False)
    assert (tmp_path / "Replica" / "room0" / "traj.txt").is_file()
    assert (tmp_path / "Replica" / "office0" / "traj.txt").stat().st_mtime_ns == office.st_mtime_ns  # left as it was

    def sequence_zip(seq: str) -> bytes:
        inner = io.BytesIO()
        with zipfile.ZipFile(inner, "w") as z:
            for k in range(2):
                z.writestr(f"{seq}/frame-{k:06d}.color.png", png(np.full((480, 640, 3), 60, np.uint8)))
                z.writestr(f"{seq}/frame-{k:06d}.depth.png", png(np.full((480, 640), 1500, np.uint16)))
                z.writestr(f"{seq}/frame-{k:06d}.pose.txt", "\n".join(" ".join(map(str, r)) for r in np.eye(4)))
        return inner.getvalue()

    outer = io.BytesIO()
    with zipfile.ZipFile(outer, "w") as z:
        z.writestr("redkitchen/seq-01.zip", sequence_zip("seq-01"))
        z.writestr("redkitchen/seq-02.zip", sequence_zip("seq-02"))
        z.writestr("redkitchen/TrainSplit.txt", "sequence1\n")
    server.files["redkitchen.zip"] = outer.getvalue()
    assert main(["7scenes/redkitchen", "--data-root", str(tmp_path), "--base-url", server.url]) == 0
    kitchen = tmp_path / "7scenes" / "redkitchen"
    assert sorted(p.name for p in kitchen.iterdir()) == ["TrainSplit.txt", "seq-01", "seq-02"]
    assert len(open_dataset(load_config(["dataset=7scenes/redkitchen", f"data_root={tmp_path}"]))) == 2


def test_the_command_lists_names_and_refuses_unknown_ones(tmp_path, capsys):
    assert main(["--list", "--data-root", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "tum/fr1_desk" in out and "rgbd_dataset_freiburg1_desk.tgz (328 MiB, SHA-256 on record)" in out
    assert "replica/office0" in out and "7scenes/redkitchen" in out and "tum/fr3_walking_xyz" in out
    assert main(["tum/fr1_dsk", "--data-root", str(tmp_path)]) == 2
    assert "Did you mean 'tum/fr1_desk'?" in capsys.readouterr().err
    assert main(["--data-root", str(tmp_path)]) == 2
    (tmp_path / "a_file").write_text("")  # a data root that is a file: said so, before any request
    assert main(["tum/fr1_desk", "--data-root", str(tmp_path / "a_file")]) == 1
    assert f"error: data root {tmp_path / 'a_file'} is a file, not a folder" in capsys.readouterr().err


def test_a_missing_dataset_names_the_download_command(tmp_path):
    with pytest.raises(DatasetError, match=f"python -m rgs_warp.download tum/fr1_desk --data-root {tmp_path}"):
        open_dataset(load_config(["dataset=tum/fr1_desk", f"data_root={tmp_path}"]))
