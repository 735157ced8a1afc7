"""The dataset loaders' errors and warnings (``rgs_warp.datasets``): intrinsics checked where they are
read, naming the file; the size a downscale leaves checked once the dataset is open; TUM says which
frames it drops and why."""

import warnings

import numpy as np
import pytest

from helpers_tum import replica_with_cam_params, tiny_tum
from rgs_warp.config import ConfigError, load_config
from rgs_warp.slam import SLAM
from rgs_warp.types import Camera

SMALL = ["device=cpu", "mapping.init_iters=10", "mapping.iters_per_frame=1", "tracking.iters=3"]


@pytest.mark.parametrize(
    "camera, message",
    [
        ({"fx": -60.0}, "fx = -60.0: a focal length"),
        ({"fx": 0.0}, "fx = 0.0: a focal length"),
        ({"fy": float("nan")}, "fy = nan"),
        ({"cx": 640.0}, "cx = 640.0: the principal point"),
        ({"scale": 0}, "scale = 0.0: the depth scale"),
        ({"distortion": [0.1, 0.2]}, r"distortion = \[0.1, 0.2\]: expected OpenCV's 4, 5, 8"),
    ],
)
def test_cam_params_errors_name_the_file(tmp_path, camera, message):
    """TUM (your own data) and Replica read cam_params.json; on 8dc16f7 these ran, or ended in a
    ZeroDivisionError or an empty trajectory."""
    from rgs_warp.datasets import DatasetError, ReplicaDataset, TUMDataset

    tum = tiny_tum(tmp_path / "tum", camera=camera)
    with pytest.raises(DatasetError, match=rf"{tum / 'cam_params.json'}: {message}"):
        TUMDataset(tum, require_pose=False)
    replica = replica_with_cam_params(tmp_path / "replica", tum / "cam_params.json")
    with pytest.raises(DatasetError, match=rf"{replica / 'cam_params.json'}: {message}"):
        ReplicaDataset(replica)


def test_sevenscenes_intrinsics_are_checked(tmp_path):
    """A negative focal length in 7-Scenes' camera-intrinsics.txt ran silently on 8dc16f7."""
    from rgs_warp.datasets import DatasetError, SevenScenesDataset

    (tmp_path / "frame-000000.color.png").write_bytes(b"")
    (tmp_path / "frame-000000.pose.txt").write_text(" ".join(map(str, np.eye(4).ravel())))
    (tmp_path / "camera-intrinsics.txt").write_text("-585 0 320\n0 585 240\n0 0 1\n")
    with pytest.raises(DatasetError, match=r"camera-intrinsics.txt: fx = -585.0: a focal length"):
        SevenScenesDataset(tmp_path, register_depth=False)
    (tmp_path / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n0 0 1\n")
    with pytest.raises(DatasetError, match=r"dataset.colour_intrinsics \(526.0, 526.0, 900.0, 238.0\): cx = 900.0"):
        SevenScenesDataset(tmp_path, colour_intrinsics=(526.0, 526.0, 900.0, 238.0))


def test_a_frame_of_another_size_names_its_file(tmp_path):
    """The lens's remap and 7-Scenes' depth registration produce the calibration's size whatever they are
    given: a 320x240 colour image in a 640x480 7-Scenes sequence had been resampled into a 640x480 frame
    of the wrong content without a word (one frame lost later), a TUM depth image of another size with a lens
    likewise.  Each loader checks its images' size where it reads them (``check_frame_size``), naming the file."""
    import cv2

    from rgs_warp.datasets import DatasetError, SevenScenesDataset, TUMDataset

    seven = tmp_path / "seven"
    seven.mkdir()
    for i, (w, h) in enumerate([(640, 480), (320, 240)]):
        cv2.imwrite(str(seven / f"frame-{i:06d}.color.png"), np.full((h, w, 3), 128, np.uint8))
        cv2.imwrite(str(seven / f"frame-{i:06d}.depth.png"), np.full((480, 640), 2000, np.uint16))
        (seven / f"frame-{i:06d}.pose.txt").write_text(" ".join(map(str, np.eye(4).ravel())))
    ds = SevenScenesDataset(seven)
    assert ds[0].rgb.shape == (480, 640, 3)
    with pytest.raises(
        DatasetError, match=r"frame-000001.color.png: colour image is 320x240, the calibration says 640x480"
    ):
        ds[1]
    cv2.imwrite(str(seven / "frame-000000.depth.png"), np.full((240, 320), 2000, np.uint16))
    with pytest.raises(
        DatasetError, match=r"frame-000000.depth.png: depth image is 320x240, the calibration says 640x480"
    ):
        ds[0]
    root = tiny_tum(tmp_path / "mine", camera={"distortion": [-0.1, 0.0, 0.0, 0.0]})
    depth_file = sorted((root / "depth").iterdir())[1]
    cv2.imwrite(str(depth_file), np.full((24, 32), 2000, np.uint16))
    with pytest.raises(DatasetError, match=r"depth/.*\.png: depth image is 32x24, the calibration says 64x48"):
        TUMDataset(root, require_pose=False)[1]


def test_missing_files_are_named_when_the_dataset_opens(tmp_path):
    """A frame file listed (TUM) or implied (7-Scenes' depth beside its colour image) but absent: an incomplete
    download had stopped the run at that frame, minutes in; now the dataset refuses to open, naming them, unless
    the selection leaves them out."""
    import cv2

    from rgs_warp.datasets import DatasetError, SevenScenesDataset, TUMDataset

    root = tiny_tum(tmp_path / "mine")
    gone = sorted((root / "rgb").iterdir())[2]
    gone.unlink()
    with pytest.raises(DatasetError, match=rf"a file of a frame is missing: {gone} \(an incomplete"):
        TUMDataset(root, require_pose=False)
    assert len(TUMDataset(root, require_pose=False, max_frames=2)) == 2  # not selected: not needed
    seven = tmp_path / "seven"
    seven.mkdir()
    for i in range(3):
        cv2.imwrite(str(seven / f"frame-{i:06d}.color.png"), np.full((480, 640, 3), 128, np.uint8))
        cv2.imwrite(str(seven / f"frame-{i:06d}.depth.png"), np.full((480, 640), 2000, np.uint16))
        (seven / f"frame-{i:06d}.pose.txt").write_text(" ".join(map(str, np.eye(4).ravel())))
    (seven / "frame-000001.depth.png").unlink()
    with pytest.raises(DatasetError, match=r"a file of a frame is missing: .*frame-000001.depth.png"):
        SevenScenesDataset(seven)


def test_colour_only_data_in_an_rgbd_run_names_the_monocular_mode(tmp_path):
    from rgs_warp.datasets import DatasetError, TUMDataset

    root = tiny_tum(tmp_path / "mine")
    (root / "depth.txt").unlink()
    with pytest.raises(
        DatasetError, match=r"depth.txt: file not found: an RGB-D run reads depth images \(colour only: mode=mono\)"
    ):
        TUMDataset(root, require_pose=False)
    assert len(TUMDataset(root, require_pose=False, require_depth=False)) == 4


def test_downscale_of_a_loaded_dataset_is_checked(tmp_path):
    """The native size of a real dataset is known once it is open: still before any run folder."""
    from rgs_warp.datasets import open_dataset

    root = tiny_tum(tmp_path / "mine")
    base = ["dataset.type=tum", f"dataset.path={root}", "dataset.require_pose=false"]
    with pytest.raises(ConfigError, match=r"dataset.downscale = 4 shrinks the 64x48 images to 16x12"):
        open_dataset(load_config([*base, "dataset.downscale=4"]))
    with pytest.raises(ValueError, match=r"the camera is 64x12"):
        SLAM(load_config(SMALL), Camera(60.0, 60.0, 31.5, 5.5, 64, 12), device="cpu")


def test_tum_says_how_many_frames_it_drops_and_why(tmp_path):
    from rgs_warp.datasets import TUMDataset

    root = tiny_tum(tmp_path / "mine", n_rgb=5, n_depth=3)
    with pytest.warns(UserWarning, match=r"2 of 5 colour frames in rgb.txt dropped: 2 without a depth image"):
        ds = TUMDataset(root, require_pose=False)
    assert len(ds) == 3 and "2 of 5 colour frames in rgb.txt dropped" in repr(ds)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing dropped: no warning
        ds = TUMDataset(tiny_tum(tmp_path / "whole", n_rgb=3, n_depth=3), require_pose=False)
    assert "dropped" not in repr(ds)


@pytest.mark.parametrize("kind", ["tum", "replica", "7scenes"])
def test_an_empty_folder_says_it_is_empty(tmp_path, kind):
    """TUM said it "cannot tell the TUM camera" of an empty folder; each loader now says it is empty."""
    from rgs_warp.datasets import DatasetError, open_dataset

    (tmp_path / "seq").mkdir()
    with pytest.raises(DatasetError, match=rf"dataset folder {tmp_path / 'seq'} is empty"):
        open_dataset(load_config([f"dataset.type={kind}", f"dataset.path={tmp_path / 'seq'}"]))


def test_depth_in_another_unit_names_the_depth_scale_that_fits(tmp_path):
    """Millimetres read as metres (a cam_params.json scale of 1): every frame was lost with "map covers
    0.0 %"; now opening the dataset names ``dataset.depth_scale`` and the value that fits."""
    from rgs_warp.datasets import DatasetError, open_dataset

    root = tiny_tum(tmp_path / "mine", camera={"scale": 1})
    base = ["dataset.type=tum", f"dataset.path={root}", "dataset.require_pose=false"]
    with pytest.raises(DatasetError, match=r"depth is 2e\+03 m at its median.*dataset.depth_scale=1000 .* as 2 m"):
        open_dataset(load_config(base))
    assert open_dataset(load_config([*base, "dataset.depth_scale=1000"]))[0].depth.max() == pytest.approx(2.0)
    assert open_dataset(load_config([*base, "mode=mono"]))  # monocular: the depth is not read
    with pytest.raises(ConfigError, match="dataset.depth_scale applies to tum, replica, 7scenes, not synthetic"):
        open_dataset(load_config(["dataset.depth_scale=1000"]))
