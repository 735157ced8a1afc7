"""The package works for a user who sets nothing up: a fresh process without the test conftest."""

import subprocess
import sys
import textwrap


def test_cpu_render_correct_without_manual_warp_config(tmp_path):
    # Tile kernels are wrong on the CPU unless wp.config.enable_cpu_blocks is set: importing
    # rgs_warp must take care of it (it once did not, and CPU renders came out nearly empty).
    code = textwrap.dedent(
        """
        import numpy as np
        from rgs_warp import Camera, GaussianMap, Renderer
        n = 400
        rng = np.random.default_rng(0)
        means = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(2.0, 2.5, n)]
        g = GaussianMap.from_numpy(means, np.tile([0, 0, 0, 1.0], (n, 1)), np.full((n, 3), np.log(0.05)),
                                   np.full(n, 3.0), np.full((n, 9, 3), 0.5), device="cpu")
        tiled = Renderer("cpu").forward(g, Camera(60.0, 60.0, 31.5, 23.5, 64, 48), np.eye(4)).alpha.numpy().copy()
        ref = Renderer("cpu", tiled=False).forward(g, Camera(60.0, 60.0, 31.5, 23.5, 64, 48), np.eye(4)).alpha.numpy()
        assert ref.mean() > 0.3, ref.mean()
        assert np.abs(tiled - ref).max() < 1e-5, np.abs(tiled - ref).max()
        print("ok")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


def test_public_api_imports_without_hidden_ties(tmp_path):
    # the README's entry points come from the package itself, and importing the SLAM does not pull in
    # the evaluation (the run module ties the two; the SLAM is usable without it)
    code = textwrap.dedent(
        """
        import sys
        import rgs_warp
        from rgs_warp import SLAM, Camera, Config, Frame, load_config, open_dataset
        assert rgs_warp.SLAM is SLAM and callable(load_config) and callable(open_dataset)
        assert "rgs_warp.eval" not in sys.modules and "rgs_warp.run" not in sys.modules, sorted(sys.modules)
        print("ok")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]
