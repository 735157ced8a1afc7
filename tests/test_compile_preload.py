"""On a GPU only (skipped without CUDA; run it on a GPU machine with ``pytest -m gpu``): after
``preload`` in a fresh process, the device's stream in Python is the one Warp's native code issues
memory operations on, and a CUDA graph that allocates and zeroes an array captures and replays.
Both failed on a one-GPU machine when force_load's threads took the primary context concurrently
(every run there crashed in its first capture with CUDA error 906)."""

import subprocess
import sys
import textwrap

import pytest
import warp as wp

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA GPU")]

SCRIPT = textwrap.dedent(
    """
    import warp as wp
    wp.config.quiet = True

    @wp.kernel
    def _fill(a: wp.array(dtype=float)):
        a[wp.tid()] = 1.0

    from rgs_warp.compile import preload
    from warp._src import context
    preload("cuda:0", workers=16)
    dev = wp.get_device("cuda:0")
    native = context.runtime.core.wp_cuda_context_get_stream(dev.context)
    print("streams", native, dev.stream.cuda_stream)
    assert native == dev.stream.cuda_stream, "the device's stream in Python is not the native current stream"
    with wp.ScopedCapture(device=dev) as capture:
        a = wp.zeros(1000, dtype=float, device=dev)
        wp.launch(_fill, dim=1000, inputs=[a], device=dev)
    wp.capture_launch(capture.graph)
    assert float(a.numpy().sum()) == 1000.0
    print("capture ok")
    """
)


def test_preload_then_capture_in_a_fresh_process(tmp_path):
    script = tmp_path / "preload_capture.py"  # a file: Warp reads a kernel's source from it
    script.write_text(SCRIPT, encoding="utf-8")
    for _ in range(3):  # a race: a fresh process each time
        out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
        assert out.returncode == 0 and "capture ok" in out.stdout, out.stdout[-2000:] + out.stderr[-3000:]
