"""The run's progress bar phases and the record of the Warp kernel modules a run loads."""

import time

import numpy as np
import warp as wp

from rgs_warp.app.progress import KernelLoads, RunProgress, watch_kernel_loads


def _fresh_kernel(step: float):
    """A kernel in a module of its own (``step`` makes its code, hence its module, new)."""

    @wp.kernel(module="unique")
    def add_step(x: wp.array(dtype=wp.float32)):
        i = wp.tid()
        x[i] = x[i] + step

    return add_step


def test_watch_kernel_loads_reports_each_module_once(device):
    kernel = _fresh_kernel(1.0)
    calls = []
    x = wp.zeros(4, dtype=wp.float32, device=device)
    with watch_kernel_loads(lambda name, cached: calls.append((name, cached))) as loads:
        wp.launch(kernel, dim=4, inputs=[x], device=device)
        wp.launch(kernel, dim=4, inputs=[x], device=device)  # loaded: not reported again
    np.testing.assert_array_equal(x.numpy(), 2.0)
    names = [name for name, *_ in loads.compiled + loads.cached]
    assert names == [kernel.module.name]
    assert calls[0][0] == kernel.module.name and calls[-1] == ("", True) and len(calls) == 2
    assert loads.load_s > 0.0 and set(loads.summary()) == {"compiled_modules", "compile_s", "cached_modules", "load_s"}
    # outside the block Warp's own loading is back
    with watch_kernel_loads() as after:
        pass
    wp.launch(_fresh_kernel(0.5), dim=4, inputs=[x], device=device)
    assert after.compiled == [] and after.cached == []


def test_progress_bar_is_silent_at_first(capsys):
    bar = RunProgress("synthetic/room0", quiet_s=60.0)
    bar.phase("opening the dataset")
    bar.close()
    assert capsys.readouterr().err == ""
    bar = RunProgress("synthetic/room0", quiet_s=0.0)
    bar.phase("opening the dataset")
    bar.close()
    assert "synthetic/room0 [opening the dataset]" in capsys.readouterr().err


def test_a_closed_bar_ends_its_line(capsys):
    # what is printed after the bar (a run's error) starts on a line of its own, also when the frames
    # started within the bar's quiet time (its clock restarts with them)
    bar = RunProgress("synthetic/room0", quiet_s=0.05)
    time.sleep(0.1)
    bar.start_frames(10)
    bar.set_postfix(fps="1.00")
    bar.close()
    err = capsys.readouterr().err
    assert "synthetic/room0 [tracking]" in err and err.endswith("\n"), repr(err[-80:])


def test_progress_bar_names_the_phase_and_the_module_compiling():
    bar = RunProgress("synthetic/room0", enabled=False)
    bar.phase("generating the scene (first use)")
    assert bar.bar.desc == "synthetic/room0 [generating the scene (first use)]"
    bar.start_frames(40)
    assert bar.bar.total == 40 and bar.bar.desc.endswith("[tracking]")
    bar.kernel_load("rgs_warp.kernels.rasterize", False)
    assert bar.bar.desc == "synthetic/room0 [compiling kernels: rasterize]"
    bar.kernel_load("", True)
    assert bar.bar.desc.endswith("[tracking]")
    bar.kernel_load("rgs_warp.kernels.ssim", True)
    assert bar.bar.desc.endswith("[loading kernels: ssim]")
    bar.close()


def test_kernel_loads_count_the_wall_time_their_loads_covered():
    """Modules compiled in parallel threads (the run's preload) overlap: the seconds reported are the span
    they covered, not the sum of each module's (which the report once gave: 74 s in a run of under a minute)."""
    loads = KernelLoads(
        compiled=[("b", 0.5, 2.0), ("a", 0.0, 1.5), ("d", 1.0, 1.2)],  # overlapping: 0.0 .. 2.0
        cached=[("c", 3.0, 3.25), ("e", 3.1, 3.2)],
    )
    assert loads.compile_s == 2.0 and loads.load_s == 2.25  # summed: 3.2 and 3.55
    assert loads.summary()["compiled_modules"] == 3 and loads.summary()["cached_modules"] == 2
    assert KernelLoads().compile_s == 0.0


def test_the_bar_says_when_a_scene_is_generated(tmp_path, monkeypatch, device):
    from rgs_warp.config import load_config
    from rgs_warp.datasets import generates_scene, open_dataset

    monkeypatch.setenv("RGS_CACHE", str(tmp_path))
    cfg = load_config(["dataset.width=32", "dataset.height=18", "dataset.n_frames=2", f"device={device}"])
    assert generates_scene(cfg)
    open_dataset(cfg, device=device)
    assert not generates_scene(cfg)
    assert generates_scene(load_config(["dataset.width=32", "dataset.height=18", "dataset.n_frames=3"]))
    assert not generates_scene(load_config(["dataset=tum/fr1_desk"]))
