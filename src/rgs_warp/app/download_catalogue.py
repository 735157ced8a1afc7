"""What ``python -m rgs_warp.download`` can fetch: each dataset name (as in ``dataset=NAME``), the folder
its loader reads (``dataset.path`` under ``data_root``), and the archive that holds it, with the
archive's size and SHA-256 where a public record gives them (``record`` says which).  An archive
without them is checked by its own CRCs (zip; gzip's trailer) and by the SHA-256 recorded at its
first download (``rgs_warp.app.download``)."""

from __future__ import annotations

from dataclasses import dataclass

TUM_URL = "https://cvg.cit.tum.de/rgbd/dataset"
REPLICA_URL = "https://cvg-data.inf.ethz.ch/nice-slam/data"  # NICE-SLAM's renders, all scenes in one zip
SEVEN_SCENES_URL = "http://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8"


@dataclass(frozen=True)
class Archive:
    base_url: str
    url_path: str  # the URL after the base, the same on a mirror (--base-url)
    unpack_to: str  # the folder under data_root its top-level folders land in
    provides: tuple[str, ...]  # those top-level folders
    size: int | None = None  # bytes
    sha256: str | None = None
    record: str = ""  # where size and SHA-256 come from
    nested_zips: bool = False  # zips inside (7-Scenes' seq-XX.zip), unpacked into the first folder it provides

    @property
    def file_name(self) -> str:
        return self.url_path.rsplit("/", 1)[-1]

    def url(self, base_url: str | None = None) -> str:
        return (base_url or self.base_url).rstrip("/") + "/" + self.url_path


@dataclass(frozen=True)
class Dataset:
    name: str  # as in dataset=NAME
    path: str  # dataset.path: the folder the loader reads, under data_root
    archive: Archive


# The measured records found in public code that pinned the official downloads (size from the server's
# Content-Length, SHA-256 of the file); fr1/desk's pair is also on record with the maintainers.
PINNED = "public code pinning the official download (size and SHA-256 measured from it)"
SIZE_ONLY = "public code's size check of the official download (no SHA-256 published)"
TUM_RECORDS = {
    "freiburg1_desk": (344_011_403, "e983d6830916e66dc4a46a71368046b149b283de87769690e7aa4e0b9483530c", PINNED),
    "freiburg1_desk2": (349_445_005, "a569e4cb453a3cd9285bc985fcb109e65f055c75b33a4b155acd9a68d96b77d2", PINNED),
    "freiburg1_xyz": (448_204_271, "a0236d97b8c30cd93b653656d2b6c293ff7c982a4130ef2a1a8beecdb124ef98", PINNED),
    "freiburg1_rpy": (410_268_381, "78103722a25873dbbb4de027eaa8c810a6382100691f02b6cf95c3adc91c4ac1", PINNED),
    "freiburg1_floor": (734_599_281, "16f8e7f13e0fc3983711b5d9db8ee663c73a5e29225b64dbe5ccaa9257e082bb", PINNED),
    "freiburg2_xyz": (2_201_854_648, "a4903027a7fe6bc6573a1ce96a8afa5689f15d74f4a3f0627e91b5799f62e40b", PINNED),
    "freiburg3_long_office_household": (
        1_483_556_251,
        "c7cd8e1afb87c80e5744a356214819b110fa09b4744fa4ba0cc2382f9ba59e9c",
        PINNED,
    ),
    "freiburg3_structure_texture_far": (
        520_806_553,
        "3f58c707f54c93b68fecd77293630e96a76d7b0f2703eb8ad9cff45ba4bbb81a",
        PINNED,
    ),
    "freiburg1_room": (782_381_450, None, SIZE_ONLY),
    "freiburg2_desk": (1_893_351_095, None, SIZE_ONLY),
}

# TUM RGB-D's sequences with public ground truth (its download page), by camera; names are
# tum/fr<camera>_<sequence> except where a config names one otherwise
TUM_SEQUENCES = {
    1: "xyz rpy 360 floor desk desk2 room plant teddy",
    2: (
        "xyz rpy 360_hemisphere 360_kidnap desk large_no_loop large_with_loop pioneer_360 pioneer_slam "
        "pioneer_slam2 pioneer_slam3 desk_with_person coke dishes flowerbouquet flowerbouquet_brownbackground "
        "metallic_sphere metallic_sphere2"
    ),
    3: (
        "long_office_household nostructure_notexture_far nostructure_notexture_near_withloop "
        "nostructure_texture_far nostructure_texture_near_withloop structure_notexture_far "
        "structure_notexture_near structure_texture_far structure_texture_near sitting_static sitting_xyz "
        "sitting_halfsphere sitting_rpy walking_static walking_xyz walking_halfsphere walking_rpy cabinet "
        "large_cabinet teddy"
    ),
}
TUM_NAMES = {"freiburg3_long_office_household": "fr3_office"}  # configs/dataset/tum/fr3_office.yaml
REPLICA_SCENES = "office0 office1 office2 office3 office4 room0 room1 room2"
SEVEN_SCENES = "chess fire heads office pumpkin redkitchen stairs"


def _tum(camera: int, sequence: str) -> Dataset:
    key = f"freiburg{camera}_{sequence}"
    folder = f"rgbd_dataset_{key}"
    size, sha256, record = TUM_RECORDS.get(key, (None, None, ""))
    archive = Archive(
        TUM_URL, f"freiburg{camera}/{folder}.tgz", "TUM", (folder,), size=size, sha256=sha256, record=record
    )
    return Dataset(f"tum/{TUM_NAMES.get(key, f'fr{camera}_{sequence}')}", f"TUM/{folder}", archive)


REPLICA = Archive(REPLICA_URL, "Replica.zip", ".", ("Replica",))


def _seven_scenes(scene: str) -> Dataset:
    archive = Archive(SEVEN_SCENES_URL, f"{scene}.zip", "7scenes", (scene,), nested_zips=True)
    return Dataset(f"7scenes/{scene}", f"7scenes/{scene}/seq-01", archive)


CATALOGUE: dict[str, Dataset] = {
    d.name: d
    for d in [
        *(_tum(camera, sequence) for camera, names in TUM_SEQUENCES.items() for sequence in names.split()),
        *(Dataset(f"replica/{scene}", f"Replica/{scene}", REPLICA) for scene in REPLICA_SCENES.split()),
        *(_seven_scenes(scene) for scene in SEVEN_SCENES.split()),
    ]
}
