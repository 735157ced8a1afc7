"""Run folders (``rgs_warp.app.rundir``): never shared by two runs, never overwritten unasked, and a
folder that is not a run's is refused rather than cleared."""

import threading
from datetime import datetime

import pytest

from rgs_warp.app.rundir import OutputError, make_run_dir
from rgs_warp.config import load_config


def test_runs_started_in_the_same_second_get_distinct_folders(tmp_path, monkeypatch):
    """8dc16f7: ``mkdir(exist_ok=True)`` on a name made of the date and second: both runs write one
    folder."""
    import rgs_warp.app.rundir as run_module

    class Frozen(datetime):
        @classmethod
        def now(cls, tz=None):
            return cls(2026, 11, 5, 12, 0, 0)

    monkeypatch.setattr(run_module, "datetime", Frozen)
    cfg = load_config([f"output_dir={tmp_path}"])
    folders = []
    threads = [threading.Thread(target=lambda: folders.append(make_run_dir(cfg))) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(folders)) == 6
    assert sorted(p.name for p in folders)[:2] == [
        "synthetic-room0-20261105-120000",
        "synthetic-room0-20261105-120000-2",
    ]


def test_an_existing_run_name_gets_a_suffix_unless_overwrite(tmp_path):
    """8dc16f7 reuses the folder, leaving the old run's metrics beside the new trajectory."""
    cfg = load_config([f"output_dir={tmp_path}", "run_name=office"])
    first = make_run_dir(cfg)
    (first / "config.yaml").write_text("old")
    (first / "metrics.json").write_text("{}")
    (first / "renders").mkdir()
    assert make_run_dir(cfg).name == "office-2" and make_run_dir(cfg).name == "office-3"
    assert (first / "metrics.json").is_file()
    again = make_run_dir(load_config([f"output_dir={tmp_path}", "run_name=office", "overwrite=true"]))
    assert again == first and list(first.iterdir()) == []  # cleared: nothing of the old run is left


def test_overwrite_refuses_a_folder_that_is_not_a_run(tmp_path):
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "thesis.tex").write_text("years of work")
    with pytest.raises(OutputError, match="not a run folder"):
        make_run_dir(load_config([f"output_dir={tmp_path}", "run_name=home", "overwrite=true"]))
    assert (tmp_path / "home" / "thesis.tex").is_file()


def test_an_output_dir_that_is_a_file_is_named(tmp_path):
    """``mkdir`` said "File exists"; the error names the path and says it is a file."""
    from rgs_warp.app.rundir import own_run_dir

    (tmp_path / "runs").write_text("")
    with pytest.raises(OutputError, match=rf"output_dir={tmp_path / 'runs'} is a file, not a folder"):
        make_run_dir(load_config([f"output_dir={tmp_path / 'runs'}"]))
    with pytest.raises(OutputError, match=rf"{tmp_path / 'runs'} as the run folder: it is a file"):
        own_run_dir(tmp_path / "runs")
