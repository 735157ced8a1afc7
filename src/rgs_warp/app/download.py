"""``python -m rgs_warp.download NAME...``: datasets fetched, checked and unpacked under ``data_root`` in
the layout their loaders read (``download_catalogue``).

A download goes to ``DATA_ROOT/.downloads/FILE.part`` and resumes from there (an HTTP Range request)
when it was interrupted.  The whole file is then checked: its size and SHA-256 against the catalogue's
record, else against the SHA-256 recorded at its first download (``.downloads/sha256.json``, written
once the archive unpacked: a zip's CRCs and gzip's trailer checked it).  An archive that fails is
removed and nothing of it is unpacked; one that passes is unpacked into a temporary folder beside the
data and moved into place, so an interrupted unpacking leaves no half-unpacked dataset.  A dataset
whose folder exists is not fetched again.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import gzip
import hashlib
import http.client
import json
import os
import shutil
import sys
import tarfile
import tempfile
import urllib.error
import urllib.request
import zipfile
import zlib
from pathlib import Path

from tqdm import tqdm

from rgs_warp.app.download_catalogue import CATALOGUE, Archive, Dataset
from rgs_warp.config import Config, group_options

CHUNK = 1 << 20
USER_AGENT = "rgs_warp-download"


class DownloadError(RuntimeError):
    """A dataset that could not be fetched or failed its checks; the message says what to do."""


def resolve(names: list[str], catalogue: dict[str, Dataset] = CATALOGUE) -> list[Dataset]:
    """The catalogue's datasets of ``names``; an unknown name is a ``DownloadError`` with the closest one."""
    out = []
    for name in names:
        if name not in catalogue:
            close = difflib.get_close_matches(name, list(catalogue), n=1, cutoff=0.5)
            hint = f" Did you mean {close[0]!r}?" if close else ""
            raise DownloadError(f"unknown dataset {name!r}.{hint} (python -m rgs_warp.download --list names them)")
        out.append(catalogue[name])
    return out


def is_present(data_root: Path, dataset: Dataset) -> bool:
    folder = data_root / dataset.path
    return folder.is_dir() and any(folder.iterdir())


def download(
    names: list[str],
    data_root: Path,
    base_url: str | None = None,
    progress: bool = True,
    catalogue: dict[str, Dataset] = CATALOGUE,
) -> list[Path]:
    """Fetch, check and unpack the datasets ``names`` under ``data_root`` (those present are left as they
    are); returns their folders.  ``base_url`` replaces each archive's server (a mirror with the same
    file names).  Raises ``DownloadError``."""
    datasets = resolve(names, catalogue)
    data_root = Path(data_root).expanduser()
    if data_root.exists() and not data_root.is_dir():
        raise DownloadError(f"data root {data_root} is a file, not a folder")
    missing = [d for d in datasets if not is_present(data_root, d)]
    for d in datasets:
        if d not in missing:
            _say(f"{d.name}: present in {data_root / d.path}")
    for archive in dict.fromkeys(d.archive for d in missing):
        wanted = [d.name for d in missing if d.archive == archive]
        _say(f"{', '.join(wanted)}: {archive.url(base_url)}")
        try:
            part = fetch(archive, data_root, base_url, progress)
            sha256 = check(archive, part, data_root)
            unpack(archive, part, data_root)
        except DownloadError:
            for folder in (data_root / archive.unpack_to, data_root / ".downloads"):  # made here, left empty
                if folder != data_root:
                    with contextlib.suppress(OSError):
                        folder.rmdir()
            raise
        _record(data_root, archive, sha256)
        part.unlink()
        for d in missing:
            if d.archive == archive and not is_present(data_root, d):
                raise DownloadError(f"{archive.file_name} unpacked, but it holds no {d.path} for {d.name}")
    return [data_root / d.path for d in datasets]


def fetch(archive: Archive, data_root: Path, base_url: str | None = None, progress: bool = True) -> Path:
    """The archive downloaded to ``data_root/.downloads/FILE.part``, resumed from what is there."""
    part = data_root / ".downloads" / f"{archive.file_name}.part"
    part.parent.mkdir(parents=True, exist_ok=True)
    offset = part.stat().st_size if part.exists() else 0
    if archive.size is not None and offset >= archive.size:
        return part  # whole already (or longer: the check refuses it)
    url = archive.url(base_url)
    headers = {"User-Agent": USER_AGENT}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    try:
        response = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=60)
    except urllib.error.HTTPError as e:
        if e.code == 416 and offset:  # nothing after offset: the file is whole
            return part
        raise DownloadError(f"{url}: HTTP {e.code} {e.reason}") from None
    except (urllib.error.URLError, OSError) as e:
        raise DownloadError(f"{url}: {getattr(e, 'reason', e)}") from None
    with response:
        resumed = offset > 0 and response.status == 206
        if resumed and not response.headers.get("Content-Range", "").startswith(f"bytes {offset}-"):
            part.unlink()
            raise DownloadError(f"{url}: the server sent another range than asked for; run again to start over")
        if offset and not resumed:  # the server ignores ranges: from the start
            offset = 0
        length = response.headers.get("Content-Length")
        total = offset + int(length) if length else archive.size
        bar = tqdm(
            total=total,
            initial=offset,
            unit="B",
            unit_scale=True,
            unit_divisor=1024,
            desc=archive.file_name,
            disable=not progress,
            file=sys.stderr,
        )
        received = 0
        try:
            with bar, open(part, "ab" if resumed else "wb") as f:
                while chunk := response.read(CHUNK):
                    f.write(chunk)
                    bar.update(len(chunk))
                    received += len(chunk)
            # http.client ends a response cut short without an error: its length tells
            why = "the connection closed early" if length and received < int(length) else ""
        except (http.client.HTTPException, OSError) as e:
            why = type(e).__name__
        if why:
            got = part.stat().st_size
            raise DownloadError(f"{url}: interrupted after {got:,} bytes ({why}); run the command again to resume")
    return part


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def check(archive: Archive, part: Path, data_root: Path) -> str:
    """The downloaded file's SHA-256 once its size and SHA-256 match the catalogue's record, or the one
    recorded at its first download; a mismatch removes the file and raises ``DownloadError``."""
    size = part.stat().st_size
    expected = archive.sha256
    source = archive.record
    if expected is None:
        expected = _records(data_root).get(archive.file_name, {}).get("sha256")
        source = f"recorded at its first download in {_records_path(data_root)}"
    sha256 = sha256_of(part) if archive.size is None or size == archive.size else ""
    if sha256 == "":
        problem = f"{size:,} bytes, {archive.size:,} expected ({archive.record})"
    elif expected is not None and sha256 != expected:
        problem = f"SHA-256 {sha256}, {expected} expected ({source})"
    else:
        problem = ""
    if problem:
        part.unlink()
        raise DownloadError(
            f"{archive.file_name}: {problem}: refused and removed (a damaged download, or a mirror's file that "
            f"differs); nothing was unpacked"
        )
    return sha256


def unpack(archive: Archive, part: Path, data_root: Path) -> None:
    """The archive's folders unpacked into ``data_root/unpack_to``: first into a temporary folder there,
    then moved into place (into a folder that exists, what it lacks); a damaged archive is removed."""
    target = data_root / archive.unpack_to
    target.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".unpacking-", dir=target))
    try:
        try:
            _extract(part, staging)
            if archive.nested_zips:
                inner = sorted(staging.rglob("*.zip"))
                for z in inner:
                    _extract(z, staging / archive.provides[0])
                    z.unlink()
        except (zipfile.BadZipFile, tarfile.TarError, gzip.BadGzipFile, zlib.error, EOFError) as e:
            part.unlink()
            raise DownloadError(
                f"{archive.file_name}: cannot be unpacked ({type(e).__name__}: {e}): removed; nothing was unpacked"
            ) from None
        absent = [name for name in archive.provides if not (staging / name).is_dir()]
        if absent:
            part.unlink()
            raise DownloadError(f"{archive.file_name}: holds no {', '.join(absent)} folder: removed (another file?)")
        for name in archive.provides:
            _move(staging / name, target / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _extract(path: Path, into: Path) -> None:
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as z:
            z.extractall(into)  # reading each member checks its CRC-32; names are kept inside ``into``
        return
    with tarfile.open(path) as t:  # gzip checks its CRC-32 at the end of the stream
        if hasattr(tarfile, "data_filter"):
            t.extractall(into, filter="data")
        else:  # Python before 3.10.12 / 3.11.4: refuse what would land outside ``into``
            root = into.resolve()
            for member in t.getmembers():
                if not (root / member.name).resolve().is_relative_to(root) or member.issym() or member.islnk():
                    raise tarfile.TarError(f"member {member.name!r} would land outside the folder")
            t.extractall(into)


def _move(source: Path, dest: Path) -> None:
    """``source`` renamed to ``dest``, or, where ``dest`` exists, what it lacks moved in (one level)."""
    if not dest.exists():
        os.replace(source, dest)
        return
    for child in source.iterdir():
        if not (dest / child.name).exists():
            os.replace(child, dest / child.name)


def _records_path(data_root: Path) -> Path:
    return data_root / ".downloads" / "sha256.json"


def _records(data_root: Path) -> dict:
    path = _records_path(data_root)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as e:
        raise DownloadError(f"{path}: unreadable ({e}); remove it to record the checksums anew") from None


def _record(data_root: Path, archive: Archive, sha256: str) -> None:
    """Remember an archive's SHA-256 that no record gave, for the next download of it."""
    if archive.sha256 is not None:
        return
    records = _records(data_root)
    if archive.file_name in records:
        return
    records[archive.file_name] = {"sha256": sha256, "url_path": archive.url_path}
    path = _records_path(data_root)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(records, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def _say(message: str) -> None:
    print(message, file=sys.stderr)


def listing(data_root: Path, catalogue: dict[str, Dataset] = CATALOGUE) -> str:
    """One line a dataset: name, archive and size, what checks it, whether it is present."""
    recorded = _records(data_root) if data_root.is_dir() else {}
    lines = []
    for d in catalogue.values():
        a = d.archive
        size = f"{a.size / 2**20:,.0f} MiB" if a.size else "size unknown"
        if a.sha256:
            check = "SHA-256 on record"
        elif a.file_name in recorded:
            check = "SHA-256 recorded here"
        else:
            check = "SHA-256 recorded at first download"
        present = "  present" if is_present(data_root, d) else ""
        lines.append(f"{d.name:<42} {a.file_name} ({size}, {check}){present}")
    return "\n".join(lines)


def run_command(dataset: Dataset, data_root: str) -> str:
    """The command that runs SLAM on a downloaded dataset."""
    root = f" data_root={data_root}" if data_root else ""
    if dataset.name in group_options("dataset"):
        return f"python -m rgs_warp.slam dataset={dataset.name}{root}"
    kind, name = dataset.name.split("/", 1)
    return f"python -m rgs_warp.slam dataset.type={kind} dataset.name={name} dataset.path={dataset.path}{root}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rgs_warp.download",
        description="Fetch datasets into data_root in the layout the loaders read (resumable, checked).",
        epilog="example: python -m rgs_warp.download tum/fr1_desk replica/office0 --data-root /data",
    )
    parser.add_argument("names", nargs="*", metavar="NAME", help="as in dataset=NAME, e.g. tum/fr1_desk")
    parser.add_argument("--data-root", default="", help="default: $RGS_DATA, else the current directory")
    parser.add_argument("--base-url", default=None, help="a mirror's address, in place of each archive's server")
    parser.add_argument("--list", action="store_true", help="the names, their archives and what is present")
    args = parser.parse_args(argv)
    data_root = Config(data_root=args.data_root).resolved_data_root()
    if args.list:
        print(listing(data_root))
        return 0
    if not args.names:
        parser.print_usage(sys.stderr)
        print("error: name at least one dataset (--list names them)", file=sys.stderr)
        return 2
    try:
        datasets = resolve(args.names)
    except DownloadError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        download(args.names, data_root, args.base_url)
    except (DownloadError, OSError) as e:  # OSError: a full disk, a folder not writable (the download stays)
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted: run the command again to resume", file=sys.stderr)
        return 130
    for d in datasets:
        print(f"{d.name} is ready: {run_command(d, args.data_root)}")
    return 0
